#version 410 core
// The stats' count of agents per LOD on the transform-feedback path (crowd/draw/feedback_cull.py): each
// agent of one character the colour pass keeps is a point added into its LOD's block of the counts
// texture (feedback_count.frag.glsl), once, at the LOD it is drawn at (across a fade, the coarser); the
// others fall outside the view. No feedback: a plain point draw costs a tenth of a feedback one.
in vec4 in_position_scale;

#include "feedback_pick.glsl"
uniform ivec2 u_count_texel;  // LOD 0's block; LOD l's is l blocks to its right
uniform int u_count_block;
uniform vec2 u_count_size;

void main() {
    Pick p = view_pick(in_position_scale);
    int id = gl_VertexID;
    vec2 texel = vec2(u_count_texel + ivec2(p.lod * u_count_block, 0) + ivec2(id & (u_count_block - 1), (id / u_count_block) & (u_count_block - 1)));
    gl_Position = p.inside ? vec4((texel + 0.5) / u_count_size * 2.0 - 1.0, 0.0, 1.0) : vec4(2.0, 2.0, 2.0, 1.0);
}
