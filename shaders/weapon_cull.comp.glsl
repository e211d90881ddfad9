#version 430
// Weapons on the GPU-driven path (crowd/draw/weapons.py): the CPU places every armed agent's weapon
// from the read-back (its 3x4 rows, sorted by weapon mesh); this pass keeps those whose agent the
// body cull (cull.comp.glsl) found visible, compacted into each weapon mesh's list, and counts them in
// that mesh's indirect command. A weapon is drawn exactly when its agent is.
layout(local_size_x = 256) in;

struct Rows { vec4 r0; vec4 r1; vec4 r2; };

layout(std430, binding = 0) readonly buffer Placed { Rows placed[]; };
layout(std430, binding = 1) readonly buffer Owner { uvec2 owner[]; };     // (agent, weapon mesh)
layout(std430, binding = 2) writeonly buffer Shown { Rows shown[]; };     // mesh w's list starts at u_start[w]
layout(std430, binding = 3) buffer Commands { uint commands[]; };
layout(std430, binding = 4) readonly buffer Visible { uint visible[]; };  // per agent, from the body cull

uniform uint u_count;
uniform uint u_mask;  // 0xFFFF: the agent is drawn (the colour pass); 0x10000: it is in the sun's volume (the shadow pass)
uniform uint u_start[16];

void main() {
    uint k = gl_GlobalInvocationID.x;
    if (k >= u_count) return;
    uvec2 o = owner[k];
    if ((visible[o.x] & u_mask) == 0u) return;
    uint slot = atomicAdd(commands[o.y * 5u + 1u], 1u);
    shown[u_start[o.y] + slot] = placed[k];
}
