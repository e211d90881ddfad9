#version 430
// Animation processor, compute path (GL 4.3): one invocation per (agent, texel of its palette row): a
// work group holds 256 / u_stride whole agents of one character (a dispatch per character of the cast,
// over its agents). An agent's row is ROW_SLOTS texels (its impostor key where IMPOSTOR_KEY, then its
// morph pairs where MORPHS), then its joints. Each joint's invocation blends its joint's local transform
// once into shared memory, then walks its chain to the root through shared memory and writes its
// skinning matrix; a slot's invocation writes the agent's key (impostor_key) or works out its morph
// pairs (morph_weights.glsl).
#include "processor_common.glsl"
#ifdef MORPHS
#include "morph_weights.glsl"
#endif

layout(local_size_x = 256) in;
layout(rgba32f, binding = 0) uniform writeonly image2DArray u_palette0;
layout(rgba32f, binding = 1) uniform writeonly image2DArray u_palette1;
layout(rgba32f, binding = 2) uniform writeonly image2DArray u_palette2;
uniform int u_agents_per_group;
uniform int u_row_offset;    // first palette row (counted across layers) of this character's block in the ring slot this run writes
uniform int u_palette_rows;  // texture rows per layer
uniform int u_stride;        // texels an agent: ROW_SLOTS, then u_joints

#ifdef IMPOSTOR_KEY
// Agents drawn only as impostors get their key and nothing else: those of the crowd on the GPU whose
// distance from the camera is past u_far_m (crowd.anim.processor.FarAgents says how far, and why safe).
layout(std430, binding = 2) readonly buffer CrowdPlaces { vec4 crowd_place[]; };  // the GPU crowd's x, z (from its origin), vx, vz
layout(std430, binding = 3) readonly buffer CrowdLooks { uvec4 crowd_look[]; };   // its tint, head, weapon + 1, spawned step
uniform vec3 u_far_eye;  // the camera, from the crowd's origin
uniform float u_far_m;   // 0: every agent's row whole
uniform int u_far_rows;  // rows the crowd holds (the survivor's after them is always whole)
uniform uint u_far_joints[8];  // a bit a joint: those a far armed agent still needs (its held weapon's socket and the socket's ancestors)

bool far_keeps(int agent, int joint) {
    return joint >= 0 && crowd_look[agent].z != 0u && ((u_far_joints[joint >> 5] >> uint(joint & 31)) & 1u) != 0u;
}

bool key_alone(int agent) {
    if (u_far_m <= 0.0 || agent >= u_far_rows) return false;
    vec3 d = vec3(crowd_place[agent].x, 0.0, crowd_place[agent].y) - u_far_eye;
    return dot(d, d) > u_far_m * u_far_m;
}
#else
bool key_alone(int agent) { return false; }
bool far_keeps(int agent, int joint) { return false; }
#endif

shared vec4 s_local0[256];
shared vec4 s_local1[256];
shared vec4 s_local2[256];
#ifdef FOOT_LOCK
#include "foot_lock.glsl"
#endif

void main() {
    int t = int(gl_LocalInvocationIndex);
    int slot = t / u_stride;
    int texel_in_row = t - slot * u_stride;
    int joint = texel_in_row - ROW_SLOTS;  // < 0: a slot
    int group = int(gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x);
    int local = group * u_agents_per_group + slot;  // among this character's agents
    int agent = u_first_agent + local;
    bool working = slot < u_agents_per_group && local < u_agents;
    bool far = working && key_alone(agent);
    bool skip = far && !far_keeps(agent, joint);  // (a kept joint's ancestors are kept: its chain reads only those)
    if (working && !skip && joint >= 0) {
        Affine m = blended_local(agent, joint);
        s_local0[t] = m.r0;
        s_local1[t] = m.r1;
        s_local2[t] = m.r2;
    }
    barrier();
    int base = slot * u_stride + ROW_SLOTS;  // the agent's joint 0 in shared memory
#ifdef FOOT_LOCK
    // The first leg's ankle invocation locks the agent's feet, leg after leg: it rewrites their locals,
    // which every invocation of the agent reads after the barrier (reached by all, working or not).
    if (working && joint == u_leg_joints[0].w) {
        for (int leg = 0; leg < LEG_COUNT; ++leg) {
            if (far) lock_state[local * LEG_COUNT + leg] = vec4(0.0);  // free, as a new agent's: it starts anew when near
            else lock_leg(local, base, leg);
        }
    }
    barrier();
#endif
    if (!working) return;
    int y = local / u_agents_per_row + u_row_offset;
    int layer = y / u_palette_rows;
    ivec3 texel = ivec3((local % u_agents_per_row) * u_stride + texel_in_row, y - layer * u_palette_rows, layer);
    if (joint < 0) {
#ifdef IMPOSTOR_KEY
        if (joint == -ROW_SLOTS) {
            imageStore(u_palette0, texel, impostor_key(agent));
            return;
        }
#endif
#ifdef MORPHS
        vec2 pairs[MORPH_PAIRS];
        if (far) {  // no target moves: the cull routes it as a plain agent (cull.comp.glsl, moves_no_target)
            for (int k = 0; k < MORPH_PAIRS; ++k) pairs[k] = vec2(0.0);
        } else {
            morph_pairs(agent, local, pairs);
        }
        imageStore(u_palette0, texel, vec4(pairs[0], pairs[1]));
        imageStore(u_palette1, texel, vec4(pairs[2], pairs[3]));
        imageStore(u_palette2, texel, vec4(pairs[4], pairs[5]));
#endif
        return;
    }
    if (skip) return;
    Affine m = Affine(s_local0[t], s_local1[t], s_local2[t]);
    int p = parent_of(joint);
    for (int k = 0; k < MAX_JOINTS && p >= 0; ++k) {
        m = compose(Affine(s_local0[base + p], s_local1[base + p], s_local2[base + p]), m);
        p = parent_of(p);
    }
#ifdef HAS_RESIDUAL
    m = scaled_axes(m, blended_residual(agent, joint));  // (its own matrix only: its children took m before)
#endif
    m = compose(m, stored_affine(joint, 0, 0));  // row 0 holds the inverse bind pose
    imageStore(u_palette0, texel, m.r0);
    imageStore(u_palette1, texel, m.r1);
    imageStore(u_palette2, texel, m.r2);
}
