#version 410 core
// Each agent's visibility for the weapons' feedback cull (crowd/draw/feedback_cull.py), the compute cull's
// `visible` word: bits 0-15 1 + its colour LOD (0: culled, or drawn as its impostor alone, which holds
// its weapon); bit 16 + k where it is in shadow cascade k's volume, with its shadow LOD in bits 20-27.
// One point per agent, into its own texel (agent i at (i % width, i / width)) of an R32UI texture.
in vec4 in_position_scale;

#include "feedback_pick.glsl"
uniform ivec2 u_size;              // the texture's, in texels

flat out uint v_visible;

void main() {
    Pick colour = view_pick(in_position_scale);
    uint word = colour.inside && !colour.held ? uint(colour.lod + 1) : 0u;
    for (int k = 0; k < u_cascades; ++k) {
        Pick lit = cascade_pick(in_position_scale, k);
        if (lit.inside && !lit.held) word |= (0x10000u << uint(k)) | (uint(lit.lod) << 20);
    }
    v_visible = word;
    ivec2 texel = ivec2(gl_VertexID % u_size.x, gl_VertexID / u_size.x);
    gl_Position = vec4((vec2(texel) + 0.5) / vec2(u_size) * 2.0 - 1.0, 0.0, 1.0);
}
