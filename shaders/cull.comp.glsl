#version 430
// The GPU-driven frame's cull (crowd/draw/gpu_cull.py): for every agent and pass (the view, then each shadow
// cascade), the lists it is in (crowd/draw/cull_lists.py: one per character, LOD and variation choice, read
// by every piece worn there), compacted by a prefix sum into one entry buffer sized by the entries an agent
// can have, not by draws x agents. Three dispatches of this shader, u_phase:
//   0 COUNT: each agent's entries, counted per work group in shared memory and added to the counts with one
//            atomic per counter the work group touched; its visibility for the weapons; the stats.
//   1 SCAN:  one work group: each list's first entry (an exclusive prefix sum over every pass's lists), the
//            draws' indirect commands from their lists' counts, and the counts zeroed for the next frame.
//   2 WRITE: each agent's entries again (the same arithmetic, so the same lists), written into its work
//            group's range of each list, reserved with one atomic per counter.
// Defines (gpu_cull.py): PASSES (1 + shadow cascades), GROUPS (the cast's variation groups), EMITS (the most
// entries one agent has over all passes), COUNTERS (PASSES x lists x 2 parts), TALLIES (COUNTERS and the
// stats' counters), SHARED_TALLIES (1: counted in shared memory first; 0: too many lists for it, every
// atomic goes to the buffer).
layout(local_size_x = 256) in;

#include "lod_pick.glsl"

struct Record {
    vec4 position_scale;  // camera-relative origin, uniform scale
    uvec4 fields;         // x: palette texel | y: tint RGB, the agent's character in the top byte | z: heading | w: choices
};

struct Character {
    vec4 bound;            // the bind pose's sphere: xyz its centre, w its radius (times the agent's scale)
    float impostor_start;  // metres from which its agents are its impostor, LOD lod_count (3e38: never)
    int lod_count;         // mesh LODs
    int steps;             // its LOD switch distances
    int starts;            // where they are in `tables` (float bits), ascending
    int table;             // where its list table is in `tables`: [lod * columns + column] -> list, or -1
    int columns;           // its common pieces' column, then every choice of every group it has
    int group_columns;     // where each group's first column is in `tables` (-1: not in that group)
    int stats;             // its first stats counter: one per LOD, its impostor's last
    int routed;            // its agents whose morph weights move nothing go to each list's STILL part
    int pad0, pad1, pad2;
};

layout(std430, binding = 0) readonly buffer Agents { Record agents[]; };
layout(std430, binding = 1) writeonly buffer Entries { uint entries[]; };      // every pass's lists, one after another
layout(std430, binding = 2) coherent buffer Counters { uint counters[]; };     // [TALLIES] counts, then [COUNTERS] cursors
layout(std430, binding = 3) coherent buffer Commands { uint commands[]; };     // [PASSES x draws] DrawElementsIndirectCommand, the stats
layout(std430, binding = 4) readonly buffer Tables { int tables[]; };
layout(std430, binding = 5) readonly buffer Characters { Character characters[]; };
// Per agent, for the weapons: bits 0-15 1 + its colour LOD (0: culled, or held by its impostor); bit 16 + k
// set where it is in shadow cascade k's volume, with its shadow LOD in bits 20-27.
layout(std430, binding = 6) writeonly buffer Visible { uint visible[]; };

const int ALL = 0, MOVING = 1, STILL = 2;  // cull_lists.py: the part of its list a draw reads

uniform int u_phase;
uniform uint u_agents;
uniform int u_lists;          // lists of one pass
uniform int u_draws;          // draws of one pass
uniform int u_draw_table;     // where the draws' (list, part) pairs are in `tables`
uniform int u_choice_table;   // where each group's (shift, bits) in fields.w are
uniform int u_stats;          // stats counters
uniform vec4 u_planes[6 * PASSES];  // the view's, then each cascade's; inside: dot(n, p) + d >= 0 (camera-relative)
uniform float u_reach[PASSES];      // metres from the eye past which an agent casts nothing into a cascade (the view: 3e38)
uniform int u_culling;
uniform float u_lod_fade;     // metres past each LOD switch over which the two LODs cross-fade (0: none; lod_fade.glsl)
uniform int u_write_visible;
uniform int u_routing;        // the processor's palette is bound: agents of routed characters may go to STILL
// Occlusion (crowd/draw/occlusion.py): the previous frame's depth pyramid and the camera it was drawn from.
uniform int u_occlusion;
uniform sampler2D u_hiz;
uniform mat4 u_hiz_view_proj;
uniform vec3 u_hiz_eye_delta;  // this frame's eye minus the pyramid's: positions relative to the pyramid's eye
uniform ivec2 u_hiz_size;      // level 0, in texels
uniform int u_hiz_levels;
#include "palette.glsl"

// Whether the sphere's bounding box lies behind what the previous frame drew there: its nearest depth
// behind the farthest depth of the pyramid texels under its screen rectangle, at the level where the
// rectangle spans at most 2 x 2 of them. A box reaching behind the camera, or out of the pyramid's view,
// is not occluded.
bool occluded(vec3 center, float radius) {
    vec3 c = center + u_hiz_eye_delta;
    vec2 lo = vec2(1.0), hi = vec2(-1.0);
    float nearest = 1.0;
    for (int k = 0; k < 8; ++k) {
        vec3 corner = c + radius * vec3((k & 1) != 0 ? 1.0 : -1.0, (k & 2) != 0 ? 1.0 : -1.0, (k & 4) != 0 ? 1.0 : -1.0);
        vec4 q = u_hiz_view_proj * vec4(corner, 1.0);
        if (q.w <= 1e-3) return false;
        vec3 ndc = q.xyz / q.w;
        lo = min(lo, ndc.xy);
        hi = max(hi, ndc.xy);
        nearest = min(nearest, ndc.z * 0.5 + 0.5);
    }
    if (any(lessThan(hi, vec2(-1.0))) || any(greaterThan(lo, vec2(1.0)))) return false;
    vec2 a = (clamp(lo, -1.0, 1.0) * 0.5 + 0.5) * vec2(u_hiz_size);
    vec2 b = (clamp(hi, -1.0, 1.0) * 0.5 + 0.5) * vec2(u_hiz_size);
    float extent = max(b.x - a.x, b.y - a.y);
    int level = clamp(int(ceil(log2(max(extent, 1.0)))), 0, u_hiz_levels - 1);
    ivec2 size = max(u_hiz_size >> level, ivec2(1));
    ivec2 ta = clamp(ivec2(a) >> level, ivec2(0), size - 1);
    ivec2 tb = clamp(ivec2(b) >> level, ivec2(0), size - 1);
    float farthest = max(max(texelFetch(u_hiz, ta, level).r, texelFetch(u_hiz, ivec2(tb.x, ta.y), level).r),
                         max(texelFetch(u_hiz, ivec2(ta.x, tb.y), level).r, texelFetch(u_hiz, tb, level).r));
    return nearest > farthest;
}

// The agent's LOD and whether it is in pass p's volume (the view with occlusion; a cascade's box one LOD
// coarser, within its reach).
Pick pass_pick(Record r, Character ch, int p) {
    vec3 center = r.position_scale.xyz + ch.bound.xyz * r.position_scale.w;
    float radius = ch.bound.w * r.position_scale.w;
    bool inside = true;
    if (u_culling != 0) {
        for (int k = 0; k < 6; ++k) inside = inside && dot(u_planes[6 * p + k].xyz, center) + u_planes[6 * p + k].w >= -radius;
        inside = inside && length(center) - radius <= u_reach[p];
        if (p == 0 && inside && u_occlusion != 0) inside = !occluded(center, radius);
    }
    float dist = length(center);
    int passed = 0;
    float last = -1.0;
    for (int k = 0; k < ch.steps; ++k) {
        float start = intBitsToFloat(tables[ch.starts + k]);
        if (dist >= start) {
            passed += 1;
            last = start;
        }
    }
    return lod_pick(inside, dist, passed, last, ch.lod_count, ch.impostor_start, u_lod_fade, p == 0 ? 0 : 1);
}

// An agent whose morph weights move nothing (the first pair the processor wrote before its joint 0 has
// weight 0) is drawn by the plain program, as if the scene had no morphs: the morph program costs 2 to 5 %
// even where it fetches nothing (docs/BENCHMARKS.md, "Morph targets").
bool moves_no_target(Record r) {
    return texelFetch(u_palette0, palette_texel(r.fields.x) - ivec3(1, 0, 0), 0).y == 0.0;
}

uint g_counter[EMITS];  // this invocation's entries: the counter each is counted on, and its value
uint g_entry[EMITS];
int g_emits = 0;

void emit(int list, int p, int part, uint entry) {
    if (list < 0) return;
    g_counter[g_emits] = uint(((p * u_lists + list) << 1) + part);
    g_entry[g_emits] = entry;
    g_emits += 1;
}

uniform int u_held_group;   // the group of the weapons impostors hold (crowd.draw.impostors.HELD_GROUP); -1: none
uniform float u_held_px;   // in the view, an impostor whose bound spans fewer pixels holds none (crowd.draw.splat.HELD_PX; 0: always)
uniform float u_focal_px;  // the view's pixels a metre spans at a metre's depth

// Pass p's entries of agent i: on each side of a fade (only the coarser outside one), its common pieces'
// list and one list per group it has, the one of its choice there.
void add_entries(uint i, Record r, Character ch, Pick pick, int p, int part) {
    if (!pick.inside) return;
    float scale = r.position_scale.w;
    bool unarmed = p == 0 && pick.held && 2.0 * ch.bound.w * scale * u_focal_px < u_held_px * length(r.position_scale.xyz + ch.bound.xyz * scale);
    for (int side = pick.fading ? 0 : 1; side < 2; ++side) {
        int row = ch.table + (side == 0 ? pick.finer : pick.lod) * ch.columns;
        uint entry = i | ((pick.fading ? (uint(side) << 7) | pick.through : 255u) << 24);
        emit(tables[row], p, part, entry);
        for (int g = 0; g < GROUPS; ++g) {
            int column = tables[ch.group_columns + g];
            if (column >= 0) {
                int bits = tables[u_choice_table + 2 * g + 1];
                uint mask = bits >= 32 ? 0xFFFFFFFFu : (1u << uint(bits)) - 1u;
                uint choice = g == u_held_group && unarmed ? 0u : (r.fields.w >> uint(tables[u_choice_table + 2 * g])) & mask;  // (0: none)
                emit(tables[row + column + int(choice)], p, part, entry);
            }
        }
    }
}

shared uint s_scan[256];

void scan(uint local) {
    uint lists = uint(PASSES * u_lists);
    uint per = (lists + 255u) / 256u;
    uint first = min(local * per, lists), last = min(first + per, lists);
    uint sum = 0u;
    for (uint l = first; l < last; ++l) sum += counters[2u * l] + counters[2u * l + 1u];
    s_scan[local] = sum;
    barrier();
    for (uint offset = 1u; offset < 256u; offset <<= 1u) {  // Hillis-Steele, inclusive
        uint v = local >= offset ? s_scan[local - offset] : 0u;
        barrier();
        s_scan[local] += v;
        barrier();
    }
    uint base = s_scan[local] - sum;
    for (uint l = first; l < last; ++l) {  // each part's cursor starts at its first entry
        uint moving = counters[2u * l];
        counters[TALLIES + 2u * l] = base;
        counters[TALLIES + 2u * l + 1u] = base + moving;
        base += moving + counters[2u * l + 1u];
    }
    memoryBarrierBuffer();
    barrier();
    uint draws = uint(PASSES * u_draws);
    for (uint k = local; k < draws; k += 256u) {
        uint d = k % uint(u_draws);
        uint l = (k / uint(u_draws)) * uint(u_lists) + uint(tables[u_draw_table + 2 * int(d)]);
        int part = tables[u_draw_table + 2 * int(d) + 1];
        uint moving = counters[2u * l], still = counters[2u * l + 1u], start = counters[TALLIES + 2u * l];
        commands[k * 5u + 1u] = part == ALL ? moving + still : (part == MOVING ? moving : still);
        commands[k * 5u + 4u] = part == STILL ? start + moving : start;
    }
    for (uint s = local; s < uint(u_stats); s += 256u) commands[draws * 5u + s] = counters[COUNTERS + s];
    memoryBarrierBuffer();
    barrier();
    for (uint t = local; t < uint(TALLIES); t += 256u) counters[t] = 0u;
}

#if SHARED_TALLIES
shared uint s_count[TALLIES];
shared uint s_base[COUNTERS];
#endif

void main() {
    uint local = gl_LocalInvocationIndex;
    if (u_phase == 1) {
        scan(local);
        return;
    }
#if SHARED_TALLIES
    for (uint t = local; t < uint(TALLIES); t += 256u) s_count[t] = 0u;
    memoryBarrierShared();
    barrier();
#endif
    uint i = gl_GlobalInvocationID.x;
    int stat = -1;
    if (i < u_agents) {
        Record r = agents[i];
        Character ch = characters[r.fields.y >> 24];
        int part = ch.routed != 0 && u_routing != 0 && moves_no_target(r) ? 1 : 0;
        uint seen = 0u;
        for (int p = 0; p < PASSES; ++p) {
            Pick pick = pass_pick(r, ch, p);
            add_entries(i, r, ch, pick, p, part);
            bool drawn = pick.inside && !pick.held;
            if (p == 0) {
                stat = g_emits > 0 ? COUNTERS + ch.stats + pick.lod : -1;
                seen = drawn ? uint(pick.lod + 1) : 0u;
            } else if (drawn) {
                seen |= (0x10000u << uint(p - 1)) | (uint(pick.lod) << 20);
            }
        }
        if (u_phase == 0 && u_write_visible != 0) visible[i] = seen;
    }
    if (u_phase == 0) {
#if SHARED_TALLIES
        for (int e = 0; e < g_emits; ++e) atomicAdd(s_count[g_counter[e]], 1u);
        if (stat >= 0) atomicAdd(s_count[stat], 1u);
        memoryBarrierShared();
        barrier();
        for (uint t = local; t < uint(TALLIES); t += 256u) {
            if (s_count[t] > 0u) atomicAdd(counters[t], s_count[t]);
        }
#else
        for (int e = 0; e < g_emits; ++e) atomicAdd(counters[g_counter[e]], 1u);
        if (stat >= 0) atomicAdd(counters[stat], 1u);
#endif
        return;
    }
#if SHARED_TALLIES
    uint slot[EMITS];
    for (int e = 0; e < g_emits; ++e) slot[e] = atomicAdd(s_count[g_counter[e]], 1u);
    memoryBarrierShared();
    barrier();
    for (uint c = local; c < uint(COUNTERS); c += 256u) {
        if (s_count[c] > 0u) s_base[c] = atomicAdd(counters[TALLIES + c], s_count[c]);
    }
    memoryBarrierShared();
    barrier();
    for (int e = 0; e < g_emits; ++e) entries[s_base[g_counter[e]] + slot[e]] = g_entry[e];
#else
    for (int e = 0; e < g_emits; ++e) entries[atomicAdd(counters[TALLIES + g_counter[e]], 1u)] = g_entry[e];
#endif
}
