#version 330 core
// Animation processor, GL 3.3 path: one fragment per (agent, texel of its row: ROW_SLOTS texels (its
// impostor key, its morph pairs), then its joints) with x = agents' slot * u_stride + ROW_SLOTS + joint
// and y = palette row within the ring slot (the layer's rows, after the slot's earlier layers); a draw
// per character of the cast covers its block of rows, from u_first_row. A fragment cannot share its neighbours' work, so it blends every ancestor of
// its joint itself, in the same order as the compute path, and writes the three rows of the skinning
// matrix at once through three render targets.
#include "processor_common.glsl"
#ifdef MORPHS
#include "morph_weights.glsl"
#endif

layout(location = 0) out vec4 o_row0;
layout(location = 1) out vec4 o_row1;
layout(location = 2) out vec4 o_row2;
flat in int g_layer;         // the layer within this run's ring slot
uniform int u_palette_rows;  // texture rows per layer
uniform int u_first_row;     // this character's first row in the ring slot
uniform int u_stride;        // texels an agent: ROW_SLOTS (impostor key, morph pairs), then u_joints

void main() {
    int x = int(gl_FragCoord.x);
    int y = int(gl_FragCoord.y) + g_layer * u_palette_rows;  // the agents' row within the slot
    int slot = x / u_stride;
    int joint = x - slot * u_stride - ROW_SLOTS;
    int agent = u_first_agent + (y - u_first_row) * u_agents_per_row + slot;
    if (joint < 0) {  // the agent's impostor key or morph pairs
#ifdef IMPOSTOR_KEY
        if (joint == -ROW_SLOTS) {
            o_row0 = impostor_key(agent);
            o_row1 = o_row2 = vec4(0.0);
            return;
        }
#endif
#ifdef MORPHS
        vec2 pairs[MORPH_PAIRS];
        morph_pairs(agent, agent - u_first_agent, pairs);
        o_row0 = vec4(pairs[0], pairs[1]);
        o_row1 = vec4(pairs[2], pairs[3]);
        o_row2 = vec4(pairs[4], pairs[5]);
#endif
        return;
    }
    Affine m = blended_local(agent, joint);
    int p = parent_of(joint);
    for (int k = 0; k < MAX_JOINTS && p >= 0; ++k) {
        m = compose(blended_local(agent, p), m);
        p = parent_of(p);
    }
    m = compose(m, stored_affine(joint, 0, 0));  // row 0 holds the inverse bind pose
    o_row0 = m.r0;
    o_row1 = m.r1;
    o_row2 = m.r2;
}
