// What every cull-and-LOD dispatch shares (shaders/cull.comp.glsl, and the prefix-sum variant that
// crowd-bench compaction measures against it, shaders/bench/cull_prefix.comp.glsl): the buffers, the
// uniforms, and which (piece, LOD) draws one agent is in.
struct Record {
    vec4 position_scale;  // camera-relative origin, uniform scale
    uvec4 fields;         // x: palette texel of joint 0 | y: tint | z: heading | w: variation choices, 4 bits a group
                          // (groups 0-6), and the agent's character in bits 28-31
};

layout(std430, binding = 0) readonly buffer Agents { Record agents[]; };
layout(std430, binding = 1) writeonly buffer Lists { Record lists[]; };  // draw d's list starts at u_record_base + list_start[d]
layout(std430, binding = 2) buffer Commands { uint commands[]; };        // DrawElementsIndirectCommand x draws
layout(std430, binding = 3) readonly buffer DrawOf { int draw_of[]; };    // [lod * u_slots + slot] -> draw, or -1
// Per agent, for the weapons: bits 0-15 1 + its colour LOD (0: culled); bit 16 + k set where it is in
// shadow cascade k's volume, with its shadow LOD in bits 20-23.
layout(std430, binding = 4) buffer Visible { uint visible[]; };
// Where each draw's list starts: the draws before it hold as many records as their characters have agents.
layout(std430, binding = 6) readonly buffer ListStart { uint list_start[]; };
// Morph routing (crowd/draw/gpu_cull.py): per draw, the plain twin of a draw with morph targets (>= 0),
// FILLS_DOWN for a twin (it shares its morph draw's list, filled from the end), or -1.
layout(std430, binding = 7) readonly buffer Route { int route[]; };
const int FILLS_DOWN = -2;

const int MAX_CAST = 16;    // characters (crowd.frame.MAX_CAST): 4 bits of fields.w
const int MAX_GROUPS = 7;   // variation groups: 4 bits each below the character's
uniform vec4 u_planes[6];   // inside: dot(n, p) + d >= 0 (camera-relative)
uniform vec4 u_bound[MAX_CAST];  // per character: xyz the bind pose's sphere centre, w its radius (both times the agent's scale)
uniform float u_margin;     // metres added to each radius (agents just outside may shadow into view)
uniform float u_reach;      // a shadow cascade's: agents whose sphere starts farther from the eye cast nothing into it
uniform float u_lod_start[4];
uniform int u_lod_steps;    // LOD distances in use
uniform int u_lod_count[MAX_CAST];  // per character: its mesh LODs
uniform float u_lod_fade;   // metres past each LOD switch over which the two LODs cross-fade (0: none; lod_fade.glsl)
uniform float u_impostor_start[MAX_CAST];  // per character: metres from which its agents are its impostor, LOD u_lod_count (crowd/draw/impostors.py)
uniform int u_culling;
uniform uint u_agents;
uniform int u_slots;        // slots per LOD in draw_of
uniform int u_common_first[MAX_CAST];  // character c's pieces every one of its agents wears: slots u_common_first[c] ..
uniform int u_common[MAX_CAST];        // .. + u_common[c] - 1
uniform int u_groups;
uniform int u_group_slot[MAX_CAST * MAX_GROUPS];  // character c's choice k of group g is slot u_group_slot[c * MAX_GROUPS + g] + k (-1: none)
uniform int u_write_visible;  // 1: the colour run writes 1 + LOD; 2: a shadow run marks its cascade's volume
uniform int u_cascade;       // the shadow run's cascade
uniform int u_list_base;     // draws before this run's in the commands (a cascade's: cascade * draws)
uniform uint u_record_base;  // records before this run's lists (a cascade's: cascade * every draw's capacity)
uniform int u_draws;       // draws in the commands buffer
uniform int u_lod_bias;    // 1 for the shadow lists: one LOD coarser than the colour pass picks
// Occlusion (crowd/draw/occlusion.py): the previous frame's depth pyramid and the camera it was drawn from.
uniform int u_occlusion;
uniform sampler2D u_hiz;
uniform mat4 u_hiz_view_proj;
uniform vec3 u_hiz_eye_delta;  // this frame's eye minus the pyramid's: positions relative to the pyramid's eye
uniform ivec2 u_hiz_size;      // level 0, in texels
uniform int u_hiz_levels;
// Characters (bit c) whose agents moving no morph target go to their pieces' plain twins: the first
// (target, weight) pair the processor wrote before the agent's joint 0 has weight 0.
uniform uint u_routing;
#include "palette.glsl"

const int MAX_DRAWS = 256;  // draws the shared counters hold (CrowdRenderer checks)
const int MAX_EMITS = 16;   // draws one agent can be in: its common pieces and one piece per group
// Whether the sphere's bounding box lies behind what the previous frame drew there: its nearest depth
// behind the farthest depth of the pyramid texels under its screen rectangle, at the level where
// the rectangle spans at most 2 x 2 of them. A box reaching behind the camera, or out of the
// pyramid's view, is not occluded.
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

// An agent of a routed character whose weights move nothing is drawn by the plain program, as if the
// scene had no morphs: the morph program costs 2 to 5 % even where it fetches nothing
// (docs/BENCHMARKS.md, "Morph targets").
bool moves_no_target(Record r, int character) {
    if (((u_routing >> uint(character)) & 1u) == 0u) return false;
    return texelFetch(u_palette0, palette_texel(r.fields.x) - ivec3(1, 0, 0), 0).y == 0.0;
}

int routed(int d, bool still) {
    return still && d >= 0 && route[d] >= 0 ? route[d] : d;
}

// Per emitted draw of this invocation's agent: the fade code its copy of the record carries in its
// tint's alpha byte (lod_fade.glsl: 255, none).
uint g_fade[MAX_EMITS];
int g_character;  // this invocation's agent's character, and the LOD it is drawn at (the coarser across a fade)
int g_lod;

// Agent i's record and the draws it is in (-1 where its LOD has no mesh for a slot): `emits` of them,
// none when it is culled; within u_lod_fade of a LOD switch (not in a shadow run) the pieces of both
// LODs, with g_fade saying each copy's side and progress. Writes its visibility for the weapons as a
// side effect (u_write_visible).
int agent_draws(uint i, out Record r, out int draws[MAX_EMITS]) {
    int emits = 0;
    r = agents[i];
    int character = int(r.fields.w >> 28);
    vec4 bound = u_bound[character];
    vec3 center = r.position_scale.xyz + bound.xyz * r.position_scale.w;
    float radius = bound.w * r.position_scale.w + u_margin;
    bool inside = true;
    if (u_culling != 0) {
        for (int p = 0; p < 6; ++p) inside = inside && dot(u_planes[p].xyz, center) + u_planes[p].w >= -radius;
        inside = inside && length(center) - radius <= u_reach;
        if (inside && u_occlusion != 0) inside = !occluded(center, radius);
    }
    int lod = 0;
    bool held = false;  // drawn as its impostor alone, which holds its weapon itself (crowd/draw/impostors.py)
    if (inside) {
        float dist = length(center);
        for (int k = 0; k < u_lod_steps; ++k) lod += int(dist >= u_lod_start[k]);
        int mesh_lod = min(lod + u_lod_bias, u_lod_count[character] - 1);
        bool impostor = dist >= u_impostor_start[character];
        // The switch just behind the agent, and the LOD it switched from: within u_lod_fade of it, both.
        float boundary = impostor ? u_impostor_start[character] : (lod > 0 ? u_lod_start[lod - 1] : -1.0);
        int finer = impostor ? mesh_lod : min(lod - 1, u_lod_count[character] - 1);
        lod = impostor ? u_lod_count[character] : mesh_lod;
        bool fading = u_lod_fade > 0.0 && u_lod_bias == 0 && boundary >= 0.0 && dist < boundary + u_lod_fade && finer != lod;
        held = impostor && !fading;
        uint through = fading ? uint(clamp((dist - boundary) / u_lod_fade, 0.0, 1.0) * 127.0 + 0.5) : 0u;
        g_character = character;
        g_lod = lod;
        bool still = moves_no_target(r, character);
        for (int side = fading ? 0 : 1; side < 2; ++side) {
            int base = (side == 0 ? finer : lod) * u_slots;
            uint code = fading ? (uint(side) << 7) | through : 255u;
            for (int s = 0; s < u_common[character]; ++s) {
                g_fade[emits] = code;
                draws[emits++] = routed(draw_of[base + u_common_first[character] + s], still);
            }
            for (int g = 0; g < u_groups; ++g) {
                int first = u_group_slot[character * MAX_GROUPS + g];
                if (first >= 0) {
                    g_fade[emits] = code;
                    draws[emits++] = routed(draw_of[base + first + int((r.fields.w >> uint(4 * g)) & 15u)], still);
                }
            }
        }
    }
    // The weapons' cull reads this: an agent whose impostor holds its weapon has none placed.
    if (u_write_visible == 1) visible[i] = inside && !held ? uint(lod + 1) : 0u;
    else if (u_write_visible == 2 && inside && !held) atomicOr(visible[i], (0x10000u << uint(u_cascade)) | (uint(lod) << 20));
    return emits;
}

shared uint s_count[MAX_DRAWS];  // per draw: the agents of this work group in it

// This invocation's agent: its record, its draws and its slot among this work group's agents in each
// of them, counted in shared memory (s_count holds the group's counts after). Every invocation of
// the work group calls it, as it holds barriers.
int count_in_group(out Record r, out int draws[MAX_EMITS], out uint slots[MAX_EMITS]) {
    uint i = gl_GlobalInvocationID.x;
    for (uint d = gl_LocalInvocationIndex; d < uint(u_draws); d += gl_WorkGroupSize.x) s_count[d] = 0u;
    memoryBarrierShared();
    barrier();
    int emits = 0;
    if (i < u_agents) {
        emits = agent_draws(i, r, draws);
        for (int e = 0; e < emits; ++e) {
            if (draws[e] >= 0) slots[e] = atomicAdd(s_count[draws[e]], 1u);
        }
    }
    memoryBarrierShared();
    barrier();
    return emits;
}
