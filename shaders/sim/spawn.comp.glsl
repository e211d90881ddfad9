#version 430
// The GPU twin of crowd.sim.spawn's spawn anywhere (a crowd's start, a resize's new agents): each agent
// of one character's run of rows from the keyed draws alone, so that a new crowd or a bigger one is a
// dispatch, not its rows sent from the CPU. The numpy AI spawns the same agents from the same draws.
layout(local_size_x = 256) in;
#include "sim/agents.glsl"
#include "sim/draws.glsl"
#ifdef TOWN
#include "sim/obstacles.glsl"
#endif
layout(std430, binding = 10) buffer Ground { vec2 ground_[]; };  // where the foot lock last saw each agent

uniform int u_first, u_count, u_kind, u_steps, u_health;
uniform float u_half;
uniform vec2 u_player;                       // where the player stood, relative to the origin
uniform float u_start_clear;
uniform uvec2 u_base_place[PLACE_TRIES];     // the keyed draws' bases: each try of a start place
uniform uvec2 u_base_traits, u_base_looks, u_base_arms;
uniform vec2 u_speed, u_reaction;            // (lowest, highest)
uniform uint u_runner_below, u_armed_below;  // a share as the bound a draw's bits stay below
uniform uint u_tints[TINT_COUNT];            // RGBA8
uniform int u_heads, u_weapons, u_weapon_first;
uniform float u_walk_speed, u_run_speed;
const float PI = 3.14159265358979;

bool unfit(vec2 p) {  // crowd.sim.spawn._unfit_start
    vec2 off = p - u_player;
    bool bad = off.x * off.x + off.y * off.y < u_start_clear * u_start_clear;
#ifdef TOWN
    bad = bad || obstacle_distance(p) < CLEARANCE + 0.1;
#endif
    return bad;
}

void main() {
    int local = int(gl_GlobalInvocationID.x);
    if (local >= u_count) return;
    int i = u_first + local;
    uint a = uint(i);
    vec2 p;
    for (int attempt = 0; attempt < PLACE_TRIES; attempt++) {
        p = vec2(-u_half) + 2.0 * u_half * vec2(keyed_draw(u_base_place[attempt], a, 0u), keyed_draw(u_base_place[attempt], a, 1u));
        if (!unfit(p)) break;
    }
#ifdef TOWN
    p = keep_out(p, u_half);
#endif
    float yaw = -PI + 2.0 * PI * keyed_draw(u_base_traits, a, 0u);
    float speed = u_speed.x + (u_speed.y - u_speed.x) * keyed_draw(u_base_traits, a, 2u);
    bool runner = keyed_bits(u_base_looks, a, 0u) < u_runner_below;
    bool armed = keyed_bits(u_base_arms, a, 0u) < u_armed_below && u_weapons > 0;
    int weapon = armed ? u_weapon_first + keyed_pick(u_base_arms, a, 1u, max(u_weapons, 1)) : -1;
    motion_[i] = vec4(p, 0.0, 0.0);
    ground_[i] = p;
    heading_[i] = vec4(sin(yaw), cos(yaw), keyed_draw(u_base_traits, a, 1u), 0.92 + 0.16 * keyed_draw(u_base_looks, a, 1u));
    timers_[i] = vec4(0.0);
    goal_[i] = vec4(p, 2.0 * keyed_draw(u_base_arms, a, 2u), u_reaction.x + (u_reaction.y - u_reaction.x) * keyed_draw(u_base_traits, a, 3u));
    traits_[i] = vec4(speed, u_walk_speed * speed, (runner ? u_run_speed : u_walk_speed) * speed, runner ? 1.0 : 0.0);
    codes_[i] = ivec4(WANDER, NO_ACTION, u_health, u_kind);
    looks_[i] = uvec4(u_tints[keyed_pick(u_base_looks, a, 2u, TINT_COUNT)], uint(keyed_pick(u_base_looks, a, 3u, u_heads)),
                      uint(weapon + 1), uint(u_steps));
}
