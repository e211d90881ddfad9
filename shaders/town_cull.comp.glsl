#version 430
// The town's placements culled on the GPU (crowd/draw/town.py): one invocation per placement of the
// districts in sight, its sphere tested against the view and, for a piece that casts a shadow, each
// cascade's volume, as the numpy cull tests it; a kept placement is copied into its pass's instances, in
// its piece's region, and counted in that (pass, piece)'s indirect command.
//
// Defines: PASSES (1, or 1 + the cascades).
layout(local_size_x = 64) in;

struct Placement { float x, y, z; uint heading, tint; };  // town.vert.glsl's instance, from the districts' anchor
layout(std430, binding = 0) readonly buffer Placed { Placement placed_[]; };
layout(std430, binding = 1) readonly buffer Info { uvec2 info_[]; };  // radius (float bits), piece | casts << 16
layout(std430, binding = 2) buffer Commands { uint commands_[]; };  // per pass and piece: count, instances, first index, base vertex, base instance
layout(std430, binding = 3) writeonly buffer View { Placement view_[]; };
#if PASSES > 1
layout(std430, binding = 4) writeonly buffer Cascade0 { Placement cascade0_[]; };
#endif
#if PASSES > 2
layout(std430, binding = 5) writeonly buffer Cascade1 { Placement cascade1_[]; };
#endif

uniform int u_count;
uniform int u_pieces;
uniform vec3 u_anchor_rel;      // the districts' anchor, relative to the camera
uniform vec4 u_planes[6 * PASSES];
uniform float u_reach[PASSES];  // metres from the eye a sphere may start at

bool seen(int p, vec3 c, float r) {
    for (int k = 0; k < 6; ++k) {
        if (dot(u_planes[6 * p + k].xyz, c) + u_planes[6 * p + k].w < -r) return false;
    }
    return length(c) - r <= u_reach[p];
}

void keep(int p, int piece, Placement q) {
    int command = (p * u_pieces + piece) * 5;
    uint at = commands_[command + 4] + atomicAdd(commands_[command + 1], 1u);
    if (p == 0) view_[at] = q;
#if PASSES > 1
    else if (p == 1) cascade0_[at] = q;
#endif
#if PASSES > 2
    else cascade1_[at] = q;
#endif
}

void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= u_count) return;
    Placement q = placed_[i];
    uvec2 info = info_[i];
    float r = uintBitsToFloat(info.x);
    int piece = int(info.y & 0xFFFFu);
    vec3 c = u_anchor_rel + vec3(q.x, q.y, q.z);
    if (seen(0, c, r)) keep(0, piece, q);
    if ((info.y >> 16) == 0u) return;
    for (int p = 1; p < PASSES; ++p) {
        if (seen(p, c, r)) keep(p, piece, q);
    }
}
