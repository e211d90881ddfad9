#version 430
// One level of the depth pyramid (crowd/draw/occlusion.py): each texel holds the farthest depth of
// the texels it covers one level finer, so a bound whose nearest point lies behind it is hidden by
// what the previous frame drew. Level 0 comes from the frame's depth texture (2x2 texels each), the
// others from the level before. A finer level of odd size has one row or column more than twice
// this one's: the last texels take it in too, so nothing is left uncovered.
layout(local_size_x = 8, local_size_y = 8) in;

layout(binding = 0) uniform sampler2D u_depth;             // level 0's source: the depth texture (compare off)
layout(r32f, binding = 0) uniform readonly image2D u_finer; // the other levels' source
layout(r32f, binding = 1) uniform writeonly image2D u_level;
uniform int u_from_depth;
uniform ivec2 u_finer_size;
uniform ivec2 u_size;

float finer(ivec2 p) {
    p = min(p, u_finer_size - 1);
    return u_from_depth != 0 ? texelFetch(u_depth, p, 0).r : imageLoad(u_finer, p).r;
}

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (any(greaterThanEqual(p, u_size))) return;
    ivec2 q = 2 * p;
    float d = max(max(finer(q), finer(q + ivec2(1, 0))), max(finer(q + ivec2(0, 1)), finer(q + ivec2(1, 1))));
    bool last_x = p.x == u_size.x - 1 && (u_finer_size.x & 1) == 1;
    bool last_y = p.y == u_size.y - 1 && (u_finer_size.y & 1) == 1;
    if (last_x) d = max(d, max(finer(q + ivec2(2, 0)), finer(q + ivec2(2, 1))));
    if (last_y) d = max(d, max(finer(q + ivec2(0, 2)), finer(q + ivec2(1, 2))));
    if (last_x && last_y) d = max(d, finer(q + ivec2(2, 2)));
    imageStore(u_level, p, vec4(d));
}
