#version 330 core
// Animation processor, GL 3.3 path: one fragment per (agent, texel of its row: ROW_SLOTS texels (its
// impostor key, its morph pairs), then its joints) with x = agents' slot * u_stride + ROW_SLOTS + joint
// and y = palette row within the ring slot (the layer's rows, after the slot's earlier layers); a draw
// per character of the cast covers its block of rows, from u_first_row.
//
// Two draws, because a fragment cannot share work with its neighbours as the compute path's work group
// does through shared memory:
//   LOCALS_PASS  each joint's fragment blends its joint's local transform once (the layers' sampling, the
//                costly part) into a scratch of the slot's shape (three targets, a row of the matrix each,
//                and a fourth, the joint's own non-uniform scale, where the character has one);
//   otherwise    each joint's fragment composes its chain to the root from the scratch's texels (three
//                fetches an ancestor, no sampling) and writes the three rows of its skinning matrix at once
//                through three render targets; the slots' fragments write the key and the morph pairs.
// The one-draw version blended every ancestor of each joint itself: 6 to 8 times the sampling for a hand,
// 63 times the compute path's time on the H200 (docs/BENCHMARKS.md, "The path without compute").
#if defined(LOCALS_PASS) && defined(HAS_RESIDUAL)
#define RESIDUAL_IN_BLEND
#elif defined(HAS_RESIDUAL)
#define RESIDUAL_PLANE
#endif
#include "processor_common.glsl"
#if defined(MORPHS) && !defined(LOCALS_PASS)
#include "morph_weights.glsl"
#endif

layout(location = 0) out vec4 o_row0;
layout(location = 1) out vec4 o_row1;
layout(location = 2) out vec4 o_row2;
#if defined(LOCALS_PASS) && defined(HAS_RESIDUAL)
layout(location = 3) out vec4 o_residual;  // the joint's own non-uniform scale, a fourth scratch plane
#endif
flat in int g_layer;         // the layer within this run's ring slot (and within the scratch)
uniform int u_palette_rows;  // texture rows per layer
uniform int u_first_row;     // this character's first row in the ring slot
uniform int u_stride;        // texels an agent: ROW_SLOTS (impostor key, morph pairs), then u_joints
#ifndef LOCALS_PASS
uniform sampler2DArray u_locals0;  // the locals pass's scratch: rows 0, 1, 2 of each joint's local transform
uniform sampler2DArray u_locals1;
uniform sampler2DArray u_locals2;
#ifdef HAS_RESIDUAL
uniform sampler2DArray u_locals3;
#endif

Affine local_of(ivec3 texel) {
    return Affine(texelFetch(u_locals0, texel, 0), texelFetch(u_locals1, texel, 0), texelFetch(u_locals2, texel, 0));
}
#endif

void main() {
    int x = int(gl_FragCoord.x);
    int y = int(gl_FragCoord.y) + g_layer * u_palette_rows;  // the agents' row within the slot
    int slot = x / u_stride;
    int joint = x - slot * u_stride - ROW_SLOTS;
    int agent = u_first_agent + (y - u_first_row) * u_agents_per_row + slot;
#ifdef LOCALS_PASS
    if (joint < 0) {
        discard;  // (the slots are the second draw's)
    }
    Affine m = blended_local(agent, joint);
    o_row0 = m.r0;
    o_row1 = m.r1;
    o_row2 = m.r2;
#ifdef HAS_RESIDUAL
    o_residual = vec4(g_residual, 0.0);
#endif
#else
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
    ivec3 texel = ivec3(x, int(gl_FragCoord.y), g_layer);
    Affine m = local_of(texel);
#ifdef HAS_RESIDUAL
    vec3 own_scale = texelFetch(u_locals3, texel, 0).xyz;
#endif
    int p = parent_of(joint);
    for (int k = 0; k < MAX_JOINTS && p >= 0; ++k) {
        texel.x = x - joint + p;  // the same agent's texel of joint p
        m = compose(local_of(texel), m);
        p = parent_of(p);
    }
#ifdef HAS_RESIDUAL
    m = scaled_axes(m, own_scale);  // (its own matrix only: its children took m before)
#endif
    m = compose(m, stored_affine(joint, 0, 0));  // row 0 holds the inverse bind pose
    o_row0 = m.r0;
    o_row1 = m.r1;
    o_row2 = m.r2;
#endif
}
