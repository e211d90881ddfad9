#version 410 core
// The cull-and-LOD pass of GL 4.0 to 4.2 contexts (macOS's 4.1 core: crowd/draw/feedback_cull.py), which
// have no compute shaders: one vertex per agent of one character, drawn as a point, decides for each of
// the (up to) 4 lists this draw fills whether the agent belongs there. A list (crowd/draw/cull_lists.py) is
// a (LOD, variation group, choice) list of the colour pass or of a shadow cascade, which the draws of every
// piece listed there read; feedback_pick.glsl makes the compute cull's decision. The geometry shader
// (feedback_cull.geom.glsl) appends the agent's entry to each of its lists, one transform-feedback stream each.
// The agent: its index, and its record through the records' buffer texture (crowd/draw/records.py). The
// index comes as an attribute of 4 bytes a vertex, the size of an entry, not as gl_VertexID: llvmpipe counts
// a stream's vertices (glDrawTransformFeedbackStream) as the bytes it wrote over the capturing draw's
// vertex stride, so the two must agree.
in uint in_agent;
uniform usamplerBuffer u_agents;

#include "feedback_pick.glsl"
// The 4 lists (streams) of this draw: the pass each is of (0: colour, 1 + k: cascade k, -1: none), its
// LOD, where its variation group's choice is in fields.w (shift -1: the pieces every agent wears), and
// its choice there.
uniform ivec4 u_slot_pass;
uniform ivec4 u_slot_lod;
uniform ivec4 u_slot_shift;
uniform ivec4 u_slot_bits;
uniform uvec4 u_slot_choice;

flat out ivec4 v_emit;   // per stream: whether the agent is in that list
flat out uvec4 v_entry;  // per stream: its entry there (the agent, and the fade code in the top byte: lod_fade.glsl)

void main() {
    vec4 in_position_scale = uintBitsToFloat(texelFetch(u_agents, 2 * int(in_agent)));
    uvec4 in_fields = texelFetch(u_agents, 2 * int(in_agent) + 1);
    Pick picks[3];
    picks[0] = view_pick(in_position_scale);
    picks[1].inside = picks[2].inside = false;  // (a cascade the frame has none of holds no one)
    for (int k = 0; k < u_cascades; ++k) picks[1 + k] = cascade_pick(in_position_scale, k);
    for (int s = 0; s < 4; ++s) {
        v_emit[s] = 0;
        v_entry[s] = 0u;
        if (u_slot_pass[s] < 0) continue;
        Pick p = picks[u_slot_pass[s]];
        uint mask = u_slot_bits[s] >= 32 ? 0xFFFFFFFFu : (1u << uint(u_slot_bits[s])) - 1u;
        bool chosen = u_slot_shift[s] < 0 || ((in_fields.w >> uint(max(u_slot_shift[s], 0))) & mask) == u_slot_choice[s];
        if (!p.inside || !chosen) continue;
        bool own = p.lod == u_slot_lod[s];
        bool finer = p.fading && p.finer == u_slot_lod[s];  // across a fade, the copy at the LOD it is leaving
        v_emit[s] = int(own || finer);
        uint code = !p.fading ? 255u : own ? 128u | p.through : p.through;
        v_entry[s] = in_agent | (code << 24);
    }
}
