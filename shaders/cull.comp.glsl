#version 430
// The GPU-driven frame's cull-and-LOD pass (crowd/draw/gpu_cull.py): one invocation per agent tests
// its bounding sphere against the view frustum, picks its LOD from its distance, and appends its
// instance record to the list of every (piece, LOD) draw it appears in, counting it in that draw's
// indirect command. The colour and shadow passes then draw from those lists with render_indirect,
// so the CPU neither culls, sorts nor packs per draw. The arithmetic is the CPU path's
// (CrowdRenderer.prepare: sphere_visible, searchsorted on the LOD distances), in float32.
layout(local_size_x = 256) in;

#include "cull_common.glsl"

// Appending with one global atomic per (agent, piece) serialises on the few counters every agent
// hits (all of a far crowd is LOD2: 3 counters): on the H200 that cost 17 ms for 100,000 agents. So
// each work group counts its agents per draw in shared memory, reserves its range of each list with
// one global atomic per draw it touches, and then writes its records into the ranges.
shared uint s_base[MAX_DRAWS];
const int LOD_SLOTS = 8;  // crowd/draw/gpu_cull.py's: per character, the agents kept at each LOD, after the commands
shared uint s_agents[MAX_CAST * LOD_SLOTS];
uniform int u_count_agents;  // the colour run counts them
uniform int u_count_base;    // their first word in the commands buffer

void main() {
    uint local = gl_LocalInvocationIndex;
    for (uint c = local; c < uint(MAX_CAST * LOD_SLOTS); c += gl_WorkGroupSize.x) s_agents[c] = 0u;
    Record r;
    int draws[MAX_EMITS];
    uint slots[MAX_EMITS];
    int emits = count_in_group(r, draws, slots);  // (its barriers order the clearing above before the counting below)
    if (u_count_agents != 0 && emits > 0) atomicAdd(s_agents[g_character * LOD_SLOTS + g_lod], 1u);
    for (uint d = local; d < uint(u_draws); d += gl_WorkGroupSize.x) {
        uint count = s_count[d];
        uint command = (uint(u_list_base) + d) * 5u;
        if (count == 0u) {
            s_base[d] = 0u;
        } else if (route[d] == FILLS_DOWN) {
            // A plain twin fills its morph draw's list from the end: its baseInstance, which starts at
            // the list's end, moves down by what each work group writes (the two never overlap, as
            // each agent is in one of them). s_base is relative to the list's start, as for the others.
            atomicAdd(commands[command + 1u], count);
            s_base[d] = atomicAdd(commands[command + 4u], 0u - count) - count - (u_record_base + list_start[d]);
        } else {
            s_base[d] = atomicAdd(commands[command + 1u], count);
        }
    }
    memoryBarrierShared();
    barrier();
    for (uint c = local; c < uint(MAX_CAST * LOD_SLOTS); c += gl_WorkGroupSize.x) {
        if (s_agents[c] > 0u) atomicAdd(commands[uint(u_count_base) + c], s_agents[c]);
    }
    for (int e = 0; e < emits; ++e) {
        int d = draws[e];
        if (d >= 0) {
            Record copy = r;
            copy.fields.y = (r.fields.y & 0x00FFFFFFu) | (g_fade[e] << 24);
            lists[u_record_base + list_start[d] + s_base[d] + slots[e]] = copy;
        }
    }
}
