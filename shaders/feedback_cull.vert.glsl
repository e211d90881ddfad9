#version 410 core
// The cull-and-LOD pass of GL 4.0 to 4.2 contexts (macOS's 4.1 core: crowd/draw/feedback_cull.py), which
// have no compute shaders: one vertex per agent of one character, drawn as a point, decides for each of
// the (up to) 4 lists this draw fills whether the agent belongs there. A list is a (LOD, variation group,
// choice) list of the colour pass or of a shadow cascade, which the draws of every piece listed there
// read; feedback_pick.glsl makes the compute cull's decision. The geometry shader
// (feedback_cull.geom.glsl) appends the record to each of its lists, one transform-feedback stream each.
in vec4 in_position_scale;  // the agent's record (cull_common.glsl's Record)
in uvec4 in_fields;

#include "feedback_pick.glsl"
// The 4 lists (streams) of this draw: the pass each is of (0: colour, 1 + k: cascade k, -1: none), its
// LOD, its variation group's 4 bits in fields.w (-1: the pieces every agent wears) and its choice there.
uniform ivec4 u_slot_pass;
uniform ivec4 u_slot_lod;
uniform ivec4 u_slot_shift;
uniform uvec4 u_slot_choice;

flat out ivec4 v_emit;   // per stream: whether the agent is in that list
flat out uvec4 v_tint;   // per stream: its record's tint with the fade code in the alpha byte (lod_fade.glsl: 255, none)
out vec4 v_position_scale;
flat out uvec4 v_fields;

void main() {
    v_position_scale = in_position_scale;
    v_fields = in_fields;
    Pick picks[3];
    picks[0] = view_pick(in_position_scale);
    picks[1].inside = picks[2].inside = false;  // (a cascade the frame has none of holds no one)
    for (int k = 0; k < u_cascades; ++k) picks[1 + k] = cascade_pick(in_position_scale, k);
    for (int s = 0; s < 4; ++s) {
        v_emit[s] = 0;
        v_tint[s] = in_fields.y | 0xFF000000u;
        if (u_slot_pass[s] < 0) continue;
        Pick p = picks[u_slot_pass[s]];
        bool chosen = u_slot_shift[s] < 0 || ((in_fields.w >> uint(u_slot_shift[s])) & 15u) == u_slot_choice[s];
        if (!p.inside || !chosen) continue;
        bool own = p.lod == u_slot_lod[s];
        bool finer = p.fading && p.finer == u_slot_lod[s];  // across a fade, the copy at the LOD it is leaving
        v_emit[s] = int(own || finer);
        uint code = !p.fading ? 255u : own ? 128u | p.through : p.through;
        v_tint[s] = (in_fields.y & 0x00FFFFFFu) | (code << 24);
    }
}
