#version 430
// crowd-bench compaction (bench/compaction_probe.py): the cull's lists compacted by a prefix sum, to
// measure against the shared-memory atomics of shaders/cull.comp.glsl. Three dispatches of this one
// shader: (0) each work group counts its agents per draw; (1) one work group per draw scans those
// counts over the work groups into each group's first slot and the draw's instance count; (2) each
// work group writes its records from its first slots on. The culling, LOD and draws an agent is in
// are cull_common.glsl's, so both compact the same lists.
layout(local_size_x = 256) in;

#include "cull_common.glsl"

layout(std430, binding = 5) buffer GroupCounts { uint group_counts[]; };  // [group * u_draws + d]: a count, then a first slot
uniform int u_phase;
uniform uint u_work_groups;

shared uint s_scan[256];

void scan_draw(uint d, uint local) {
    uint per = (u_work_groups + 255u) / 256u;
    uint first = local * per;
    uint last = min(first + per, u_work_groups);
    uint sum = 0u;
    for (uint g = first; g < last; ++g) sum += group_counts[g * uint(u_draws) + d];
    s_scan[local] = sum;
    barrier();
    for (uint offset = 1u; offset < 256u; offset <<= 1u) {  // Hillis-Steele, inclusive
        uint v = local >= offset ? s_scan[local - offset] : 0u;
        barrier();
        s_scan[local] += v;
        barrier();
    }
    uint base = s_scan[local] - sum;
    for (uint g = first; g < last; ++g) {
        uint c = group_counts[g * uint(u_draws) + d];
        group_counts[g * uint(u_draws) + d] = base;
        base += c;
    }
    if (local == 255u) commands[(uint(u_list_base) + d) * 5u + 1u] = s_scan[255];
}

void main() {
    uint local = gl_LocalInvocationIndex;
    if (u_phase == 1) {
        scan_draw(gl_WorkGroupID.x, local);
        return;
    }
    uint group = gl_WorkGroupID.x;
    Record r;
    int draws[MAX_EMITS];
    uint slots[MAX_EMITS];
    int emits = count_in_group(r, draws, slots);
    if (u_phase == 0) {
        for (uint d = local; d < uint(u_draws); d += gl_WorkGroupSize.x) group_counts[group * uint(u_draws) + d] = s_count[d];
        return;
    }
    for (int e = 0; e < emits; ++e) {
        int d = draws[e];
        if (d >= 0) {
            Record copy = r;
            copy.fields.y = (r.fields.y & 0x00FFFFFFu) | (g_fade[e] << 24);
            lists[u_record_base + list_start[d] + group_counts[group * uint(u_draws) + uint(d)] + slots[e]] = copy;
        }
    }
}
