#version 430
// A uniform grid of the living agents (crowd/sim/gpu_grid.py): COUNT gives each its cell and counts
// the cells, SCAN_LOCAL / SCAN_BLOCKS / SCAN_ADD make each cell's first slot (an exclusive prefix sum),
// SCATTER puts each agent in a slot of its cell (with PAYLOAD, its point too, so a cell's neighbours
// are read from contiguous memory), ORDER sorts each cell's agents by number. Atomics
// decide only which slot an agent lands in; ORDER makes the order the numpy grid's (a stable sort by
// cell), so whatever reads a cell reads the same agents in the same order, run after run.
layout(local_size_x = 256) in;
layout(std430, binding = 0) buffer Points { vec4 points_[]; };  // x, z in .xy
layout(std430, binding = 10) buffer Cell { uint cell_[]; };      // each agent's cell (NONE: not in the grid)
layout(std430, binding = 11) buffer Count { uint count_[]; };    // agents a cell holds (0 again after ORDER)
layout(std430, binding = 12) buffer First { uint first_[]; };    // where each cell's agents start; cells + 1
layout(std430, binding = 13) buffer Blocks { uint blocks_[]; };  // the scan's block totals
layout(std430, binding = 14) buffer Sorted { uint sorted_[]; };  // agents in cell order
#ifdef LIVE_ONLY
layout(std430, binding = 5) buffer Codes { ivec4 codes_[]; };
#endif
#ifdef PAYLOAD
layout(std430, binding = 16) buffer Payload { vec4 payload_[]; };  // each slot's agent's point: a cell's neighbours read contiguous memory
#endif

uniform int u_n;
uniform int u_cells;
uniform int u_side;
uniform vec2 u_corner;  // the world's corner: cell (1, 1)'s (a ring of spare cells round the world)
uniform float u_inv_size;
const uint NONE = 0xFFFFFFFFu;

#ifdef COUNT
void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= u_n) return;
#ifdef LIVE_ONLY
    if (codes_[i].x >= 4) { cell_[i] = NONE; return; }  // the dying and the dead are nobody's neighbours
#endif
    vec2 g = clamp((points_[i].xy - u_corner) * u_inv_size + 1.0, vec2(1.0), vec2(float(u_side) - 2.0));
    uint c = uint(g.y) * uint(u_side) + uint(g.x);
    cell_[i] = c;
    atomicAdd(count_[c], 1u);
}
#endif

#if defined(SCAN_LOCAL) || defined(SCAN_BLOCKS)
shared uint s_sum[256];

uint inclusive_sum(uint local, uint value) {  // the work group's inclusive prefix sum (Hillis and Steele)
    s_sum[local] = value;
    barrier();
    for (uint offset = 1u; offset < 256u; offset <<= 1u) {
        uint add = local >= offset ? s_sum[local - offset] : 0u;
        barrier();
        s_sum[local] += add;
        barrier();
    }
    return s_sum[local];
}
#endif

#ifdef SCAN_LOCAL
void main() {
    uint local = gl_LocalInvocationID.x;
    uint c = gl_GlobalInvocationID.x;
    uint v = c < uint(u_cells) ? count_[c] : 0u;
    if (c < uint(u_cells)) count_[c] = 0u;  // SCATTER counts again from 0
    uint sum = inclusive_sum(local, v);
    if (c < uint(u_cells)) first_[c] = sum - v;
    if (local == 255u) blocks_[gl_WorkGroupID.x] = sum;
}
#endif

#ifdef SCAN_BLOCKS
// One work group: each thread sums a run of blocks in order, the runs' totals are scanned, then each
// thread writes its run's exclusive sums.
uniform int u_blocks;
void main() {
    uint local = gl_LocalInvocationID.x;
    uint per = (uint(u_blocks) + 255u) / 256u;
    uint lo = min(local * per, uint(u_blocks)), hi = min(lo + per, uint(u_blocks));
    uint total = 0u;
    for (uint b = lo; b < hi; b++) total += blocks_[b];
    uint sum = inclusive_sum(local, total);
    uint base = sum - total;
    for (uint b = lo; b < hi; b++) {
        uint v = blocks_[b];
        blocks_[b] = base;
        base += v;
    }
    if (local == 255u) first_[u_cells] = sum;
}
#endif

#ifdef SCAN_ADD
void main() {
    uint c = gl_GlobalInvocationID.x;
    if (c < uint(u_cells)) first_[c] += blocks_[gl_WorkGroupID.x];
}
#endif

#ifdef SCATTER
void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= u_n) return;
    uint c = cell_[i];
    if (c == NONE) return;
    uint slot = first_[c] + atomicAdd(count_[c], 1u);
    sorted_[slot] = uint(i);
#ifdef PAYLOAD
    payload_[slot] = points_[i];
#endif
}
#endif

#ifdef ORDER
void main() {
    uint c = gl_GlobalInvocationID.x;
    if (c >= uint(u_cells)) return;
    uint lo = first_[c], hi = lo + count_[c];
    count_[c] = 0u;  // ready for the next build's COUNT
    for (uint a = lo + 1u; a < hi; a++) {  // insertion sort: a cell holds a few agents
        uint v = sorted_[a];
#ifdef PAYLOAD
        vec4 pv = payload_[a];
#endif
        uint b = a;
        while (b > lo && sorted_[b - 1u] > v) {
            sorted_[b] = sorted_[b - 1u];
#ifdef PAYLOAD
            payload_[b] = payload_[b - 1u];
#endif
            b--;
        }
        sorted_[b] = v;
#ifdef PAYLOAD
        payload_[b] = pv;
#endif
    }
}
#endif
