// An agent's morph weights (crowd/anim/morph.py says the rules; reference_weights and active_pairs are
// the float64 twin): its layers blend the clips' weight tracks with the weights they blend the joints
// with, the agent's variation is added, and the MORPH_PAIRS largest (by size, ties by target) that are
// at least ACTIVE_WEIGHT become the (target, weight) pairs the skinned draw fetches. Included by
// processor_common.glsl where MORPHS is defined, with MORPH_COUNT (the character's targets),
// MORPH_PAIRS, ACTIVE_WEIGHT and MAX_MORPH_WEIGHT.

uniform sampler2D u_morph_tracks;     // (MORPH_COUNT, rows): row 0 the default weights, then the clips' frames
uniform isampler2D u_morph_clips;     // (clips, 1): a clip's first row and frame count (0, 1: the defaults)
uniform sampler2D u_morph_variation;  // (MORPH_COUNT, 1): lo, hi of the agents' offsets
uniform uint u_morph_seed;
uniform uint u_character;             // the character's place in the cast (its agents' variation differs)
// Weights held from the panel: a target's weight where it is >= 0 (-1: not held), for agent number
// u_morph_held_agent among the character's, or every agent (-1), or none (-2). A texture, not a uniform
// array: a character may have up to 1,024 targets, past what a compute shader's uniforms must hold.
uniform sampler2D u_morph_held;  // (MORPH_COUNT, 1)
uniform int u_morph_held_agent;

// PCG's output permutation (crowd.anim.morph.pcg_hash).
uint pcg_hash(uint v) {
    uint state = v * 747796405u + 2891336453u;
    uint word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

float morph_variation(int local, int m) {
    vec2 range = texelFetch(u_morph_variation, ivec2(m, 0), 0).xy;
    if (!(range.y > range.x)) return range.x;
    uint key = pcg_hash(u_morph_seed ^ pcg_hash(u_character * 0x9E3779B9u + uint(local) * uint(MORPH_COUNT) + uint(m)));
    return range.x + (range.y - range.x) * (float(key >> 8u) / 16777216.0);
}

// The pairs of agent `agent` (numbered `local` among its character's), largest first, then (0, 0)s.
void morph_pairs(int agent, int local, out vec2 pairs[MORPH_PAIRS]) {
    vec4 layer[LAYERS];
    float weight[LAYERS];
    int row0[LAYERS];
    int row1[LAYERS];
    float lerp_u[LAYERS];
    float unit = power_of_two_below(agent_layers(agent, layer));
    float total = 0.0;
    for (int l = 0; l < LAYERS; ++l) {
        weight[l] = max(layer[l].z, 0.0) * unit;  // no joint mask: a target is no joint
        total += weight[l];
        int clip = int(layer[l].x);
        bool looping = texelFetch(u_clips, ivec2(clip, 0), 0).w > 0.5;
        ivec2 rows = texelFetch(u_morph_clips, ivec2(clip, 0), 0).xy;
        float phase = looping ? fract(layer[l].y) : clamp(layer[l].y, 0.0, 1.0);
        float f = phase * max(float(rows.y) - 1.0, 0.0);
        float i0 = clamp(floor(f), 0.0, max(float(rows.y) - 2.0, 0.0));
        lerp_u[l] = f - i0;
        row0[l] = rows.x + int(i0);
        row1[l] = rows.x + min(int(i0) + 1, rows.y - 1);
    }
    for (int k = 0; k < MORPH_PAIRS; ++k) pairs[k] = vec2(0.0);
    bool held = u_morph_held_agent == -1 || u_morph_held_agent == local;
    for (int m = 0; m < MORPH_COUNT; ++m) {
        float w;
        if (total > 0.0) {
            float sum = 0.0;
            for (int l = 0; l < LAYERS; ++l) {
                if (weight[l] > 0.0) {
                    float a = texelFetch(u_morph_tracks, ivec2(m, row0[l]), 0).x;
                    float b = texelFetch(u_morph_tracks, ivec2(m, row1[l]), 0).x;
                    sum += weight[l] * (a + (b - a) * lerp_u[l]);
                }
            }
            w = sum / total;
        } else {
            w = texelFetch(u_morph_tracks, ivec2(m, 0), 0).x;
        }
        w = clamp(w + morph_variation(local, m), -MAX_MORPH_WEIGHT, MAX_MORPH_WEIGHT);
        if (held) {
            float h = texelFetch(u_morph_held, ivec2(m, 0), 0).x;
            if (h >= 0.0) w = h;
        }
        if (abs(w) < ACTIVE_WEIGHT) continue;
        // Into the list kept sorted by size: the pair goes down the list, swapping places with each
        // smaller one (an earlier target stays ahead of an equal one). A loop of constant bounds, so
        // the list stays in registers (the shifting insertion written first lost entries on llvmpipe).
        vec2 item = vec2(float(m), w);
        for (int k = 0; k < MORPH_PAIRS; ++k) {
            if (abs(item.y) > abs(pairs[k].y)) {
                vec2 smaller = pairs[k];
                pairs[k] = item;
                item = smaller;
            }
        }
    }
}
