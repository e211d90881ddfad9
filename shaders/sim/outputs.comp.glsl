#version 430
// The GPU twin of crowd.sim.outputs: each agent's four layers, written straight into the processor's
// input (crowd.frame's layers: clip, phase, weight, mask per layer): idle, walk and run on the shared
// phase, weighted by ground speed, and the action cross-faded in and out (an attack on the upper body).
layout(local_size_x = 256) in;
#include "sim/agents.glsl"
#include "sim/locomotion.glsl"
uniform int u_n;

#ifdef LAYERS
layout(std430, binding = 9) buffer Layers { vec4 layers_[]; };  // 4 an agent
uniform int u_first;     // the row of the first agent's layers in Layers
uniform float u_fade_len;
const float MAX_ACTION_WEIGHT = 1000.0;

void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= u_n) return;
    vec4 m = motion_[i];
    vec4 hd = heading_[i];
    vec4 tr = traits_[i];
    ivec4 c = codes_[i];
    Kind k = kinds[c.w];
    vec4 w = locomotion_weights(k, sqrt(m.z * m.z + m.w * m.w), tr.y, tr.x);
    vec4 action = vec4(0.0, 0.0, 0.0, -1.0);
    float keep = 1.0;  // what is left of the locomotion's weights
    if (c.y != NO_ACTION) {
        float elapsed = timers_[i].y;
        float span = k.length[c.y];
        float fade_in = min(elapsed * (1.0 / u_fade_len), 1.0);
        float fade_out = clamp((span - elapsed) * (1.0 / u_fade_len), 0.0, 1.0);
        float fade = min(fade_in, c.y == ACT_DEATH ? 1.0 : fade_out);
        bool upper = c.y == ACT_ATTACK && k.more.z >= 0.0;
        keep = upper ? 1.0 : 1.0 - fade;
        // Upper body: weight W against the locomotion's 1 gives the share W / (W + 1) = fade.
        action = vec4(k.clip[c.y], min(elapsed / span, 1.0),
                      upper ? min(fade / max(1.0 - fade, 1e-12), MAX_ACTION_WEIGHT) : fade, upper ? k.more.z : -1.0);
    }
    int o = (u_first + i) * 4;
    layers_[o] = vec4(k.loco_clip.x, hd.z, w.x * keep, -1.0);
    layers_[o + 1] = vec4(k.loco_clip.y, hd.z, w.y * keep, -1.0);
    layers_[o + 2] = vec4(k.loco_clip.z, hd.z, w.z * keep, -1.0);
    layers_[o + 3] = action;
}
#endif

#if defined(OVERRIDES) || defined(OVERRIDE_LIST)
// A person's overrides on top of the AI's layers (crowd.frame.LayerOverrides.apply): a forced clip
// on layer 0 (the others emptied) and held weights per layer. OVERRIDES applies those meant for every
// agent of a range, a thread an agent; OVERRIDE_LIST those meant for listed agents, a thread an entry
// (the agent, and bits: 1 << layer for a listed held weight, 16 for the forced clip), re-applying the
// range's held weights after a listed forced clip so that weights come after the clip, as in numpy.
layout(std430, binding = 9) buffer Layers { vec4 layers_[]; };
layout(std430, binding = 10) buffer Entries { ivec2 entries_[]; };
uniform int u_lo, u_hi;                 // the forced clip's character's agents
uniform bool u_forced_all;              // a forced clip on every agent of lo..hi
uniform float u_forced_clip, u_forced_phase;
uniform vec4 u_held_all;                // per layer: a weight held for everyone (-1: none)
uniform vec4 u_held_listed;             // per layer: a weight held for listed agents (-1: none)
uniform int u_entries;

void force(int i) {
    layers_[i * 4] = vec4(u_forced_clip, u_forced_phase, 1.0, -1.0);
    for (int l = 1; l < 4; l++) layers_[i * 4 + l] = vec4(0.0, 0.0, 0.0, -1.0);
}

void hold(int i, vec4 held) {
    for (int l = 0; l < 4; l++) if (held[l] >= 0.0) layers_[i * 4 + l].z = held[l];
}

void main() {
    int g = int(gl_GlobalInvocationID.x);
#ifdef OVERRIDES
    if (g >= u_n) return;
    if (u_forced_all && g >= u_lo && g < u_hi) force(g);
    hold(g, u_held_all);
#else
    if (g >= u_entries) return;
    ivec2 e = entries_[g];
    if (e.x < 0 || e.x >= u_n) return;
    if ((e.y & 16) != 0 && e.x >= u_lo && e.x < u_hi) {
        force(e.x);
        hold(e.x, u_held_all);
    }
    vec4 listed = vec4(-1.0);
    for (int l = 0; l < 4; l++) if ((e.y & (1 << l)) != 0) listed[l] = u_held_listed[l];
    hold(e.x, listed);
#endif
}
#endif

#ifdef FOOT_MOTION
// The foot lock's input (crowd.agent_rows.FootLockSteps' twin): each agent's ground step since the
// last run and its front times its scale, into one character's motion buffer; where it stood is kept.
layout(std430, binding = 9) buffer Steps { vec4 steps_[]; };
layout(std430, binding = 10) buffer Ground { vec2 ground_[]; };
uniform int u_first, u_count;

void main() {
    int g = int(gl_GlobalInvocationID.x);
    int i = u_first + g;
    if (g >= u_count || i >= u_n) return;
    vec4 m = motion_[i];
    vec4 hd = heading_[i];
    steps_[g] = vec4(m.xy - ground_[i], hd.xy * hd.w);
    ground_[i] = m.xy;
}
#endif
