#version 430
// The GPU twin of crowd.sim.think: one thread an agent. THINK_A is ThinkMixin._think_a (timers and
// transitions, respawn, wander, steering and this substep's motion); FINISH is _apply_range (the
// separation's push, a push stepped by the legs, the world's bounds) then _think_b (heading, the turn
// about the planted foot, the locomotion phase). Every agent thinks every substep: no think budget.
layout(local_size_x = 256) in;
#include "sim/agents.glsl"
#include "sim/draws.glsl"
#include "sim/locomotion.glsl"
#ifdef TOWN
#include "sim/obstacles.glsl"
#endif

uniform int u_n;
uniform float u_h;             // the substep's seconds
uniform vec2 u_player;         // relative to the origin
uniform float u_half;          // the world's half width
uniform int u_steps;           // step() calls so far (an agent's spawned_step)

#ifdef THINK_A
uniform uvec2 u_base_respawn;  // the keyed draws' base for this substep
uniform uvec2 u_base_wander;
uniform float u_notice, u_forget, u_reach, u_cooldown, u_corpse_time, u_wander_radius, u_wander_speed, u_arrive, u_max_accel;
uniform int u_health;
const float ATTACK_IMPACT = 0.5, BLOW_REACH = 1.25;

void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= u_n) return;
    vec4 m = motion_[i];
    vec4 t = timers_[i];
    vec4 g = goal_[i];
    vec4 tr = traits_[i];
    ivec4 c = codes_[i];
    Kind k = kinds[c.w];
    float h = u_h;
    vec2 to_p = u_player - m.xy;
    float dist = sqrt(to_p.x * to_p.x + to_p.y * to_p.y);
    t.x += h;
    t.y += h;
    t.z -= h;
    float span = k.length[c.y];
    if (c.x == ATTACK) {  // a blow lands at its swing's impact, on a player still within reach of it
        float impact = ATTACK_IMPACT * span;
        if (t.y >= impact && t.y - h < impact && dist < u_reach * BLOW_REACH) atomicAdd(blows, 1u);
    }
    if (t.y >= span) {
        if (c.x == ATTACK || c.x == HIT) {
            t.z = c.x == ATTACK ? u_cooldown : 0.0;
            c.x = CHASE;
            c.y = NO_ACTION;
        } else if (c.x == DYING) {
            c.x = DEAD;
            t.x = 0.0;
        }
    }
    vec4 hd = heading_[i];
    if (t.x >= u_corpse_time && c.x == DEAD) {  // respawn at an edge of the world, facing the middle
        float d0 = keyed_draw(u_base_respawn, uint(i), 0u);
        float d1 = keyed_draw(u_base_respawn, uint(i), 1u);
        float d2 = keyed_draw(u_base_respawn, uint(i), 2u);
        int side = min(int(d0 * 4.0), 3);
        float along = -u_half + 2.0 * u_half * d1;
        float edge = (side % 2 == 0 ? -1.0 : 1.0) * (u_half - 0.5);
        vec2 p = side < 2 ? vec2(edge, along) : vec2(along, edge);
        float l = length(p);
        hd.xy = l > 0.0 ? -p / l : vec2(0.0, 1.0);  // (facing the middle from the edge, before a building moves it)
#ifdef TOWN
        p = keep_out(p, u_half);  // (an edge of the world that runs through a building)
#endif
        m = vec4(p, 0.0, 0.0);
        g.xy = p;
        g.z = 2.0 * d2;
        c = ivec4(WANDER, NO_ACTION, u_health, c.w);
        t = vec4(0.0);
        looks_[i].w = uint(u_steps);
        atomicAdd(respawns, 1u);
    }
    bool near = dist < u_notice;
    t.w = near ? t.w + h : 0.0;
    if (c.x == WANDER && near && t.w >= g.w) c.x = CHASE;
    if (dist > u_forget && c.x == CHASE) c.x = WANDER;
    if (dist < u_reach && t.z <= 0.0 && c.x == CHASE && k.roles.x >= 0.0) {
        c.x = ATTACK;
        c.y = ACT_ATTACK;
        t.x = 0.0;
        t.y = 0.0;
    }
    g.z -= h;
    bool chasing = c.x == CHASE, wandering = c.x == WANDER;
    if (wandering) {
        vec2 w = g.xy - m.xy;
        if (w.x * w.x + w.y * w.y < 0.16 && g.z <= 0.0) {  // a new point to wander to
            float d0 = keyed_draw(u_base_wander, uint(i), 0u);
            float d1 = keyed_draw(u_base_wander, uint(i), 1u);
            float d2 = keyed_draw(u_base_wander, uint(i), 2u);
            float d3 = keyed_draw(u_base_wander, uint(i), 3u);
            float angle = 3.14159265358979 * (2.0 * d0 - 1.0);
            float radius = u_wander_radius * sqrt(0.1 + 0.9 * d1);
            float inner = u_half - 0.5;
            g.xy = clamp(m.xy + radius * vec2(sin(angle), cos(angle)), -inner, inner);
            g.z = d2 < 0.5 ? 1.0 + 3.0 * d3 : 0.0;
#ifdef TOWN
            g.xy = keep_out(g.xy, u_half);  // a target in a building is moved out to the street beside it
#endif
        }
    }
    vec2 d = chasing ? to_p : g.xy - m.xy;
#ifdef TOWN
    if (chasing) d = flow_direction(m.xy, to_p, dist) * dist;  // round the buildings, by the flow field
#endif
    float dl = sqrt(d.x * d.x + d.y * d.y);
    float top = chasing ? tr.z : (wandering && g.z <= 0.0 ? u_wander_speed * tr.y : 0.0);
    float gap = chasing ? dl - 0.8 * u_reach : dl;
    float speed = top * min(max(gap * (1.0 / u_arrive), 0.0), 1.0);
    float scale = speed / max(dl, 1e-9);
    vec2 change = d * scale - m.zw;
    float limit = min(1.0, (u_max_accel * h) / max(sqrt(change.x * change.x + change.y * change.y), 1e-12));
    m.zw += change * limit;
    if (c.x >= DYING) m.zw = vec2(0.0);  // the dying and the dead stop at once
    m.xy += m.zw * h;
    motion_[i] = m;
    heading_[i] = hd;
    timers_[i] = t;
    goal_[i] = g;
    codes_[i] = c;
    scratch_[i] = vec4(0.0, 0.0, to_p);
}
#endif

#ifdef FINISH
layout(std430, binding = 9) buffer Pivots { vec4 pivots_[]; };  // per character, clip (idle, walk, run) and phase sample: x, z, down
uniform float u_cos_step, u_sin_step;  // the turn limit of a substep
uniform bool u_plant_feet;
const int FOOT_SAMPLES = 64;

vec2 pivot_shift(int kind, float phase, vec3 w, vec2 h0, vec2 h1, float scale) {
    float f = phase * float(FOOT_SAMPLES);
    int s = int(clamp(floor(f), 0.0, float(FOOT_SAMPLES - 1)));
    float u = f - float(s);
    vec2 mid = vec2(0.0);
    float down = 0.0;
    for (int r = 0; r < 3; r++) {
        vec4 a = pivots_[(kind * 3 + r) * (FOOT_SAMPLES + 1) + s];
        vec4 b = pivots_[(kind * 3 + r) * (FOOT_SAMPLES + 1) + s + 1];
        float on = w[r] * min(a.z, b.z);  // a clip whose foot lifts between the two samples does not count
        mid += on * (a.xy + u * (b.xy - a.xy));
        down += on;
    }
    if (down < 0.5) return vec2(0.0);  // a run's flight: no foot to turn about
    mid *= scale / max(down, 1e-12);
    return vec2((h0.y - h1.y) * mid.x + (h0.x - h1.x) * mid.y, (h1.x - h0.x) * mid.x + (h0.y - h1.y) * mid.y);
}

void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= u_n) return;
    vec4 m = motion_[i];
    vec4 hd = heading_[i];
    vec4 tr = traits_[i];
    ivec4 c = codes_[i];
    vec4 s = scratch_[i];
    Kind k = kinds[c.w];
    // The separation's push (its pass left 0 where there is none).
    m.xy += s.xy;
    if (u_plant_feet) {  // a push along the heading moves the legs as the agent's own steps do
        float speed = sqrt(m.z * m.z + m.w * m.w);
        vec4 w = locomotion_weights(k, speed, tr.y, tr.x);
        if (w.x <= 0.5 && c.x < DYING) {
            float stride = (1.0 - w.x) * blended_stride(k, w.w, hd.w);
            float along = s.x * hd.x + s.y * hd.y;
            hd.z = advance_phase(hd.z, along / max(stride, 1e-9));
        }
    }
    // The world's bounds: clamp, and stop the velocity that points out.
    if (m.x < -u_half || m.x > u_half) { m.x = clamp(m.x, -u_half, u_half); m.z = 0.0; }
    if (m.y < -u_half || m.y > u_half) { m.y = clamp(m.y, -u_half, u_half); m.w = 0.0; }
#ifdef TOWN
    {  // out of the obstacles, the velocity into them stopped: agents slide along a wall
        vec2 cell = floor(mod(m.xy + u_origin_mod, u_period) / u_cell);
        if (field_at(int(cell.x) % u_field_n, int(cell.y) % u_field_n) < CLEARANCE + u_cell) {
            vec2 out_ = keep_out(m.xy, u_half);
            if (out_ != m.xy) {
                m.xy = out_;
                vec2 n = obstacle_gradient(m.xy);
                m.zw -= min(dot(m.zw, n), 0.0) * n;
            }
        }
    }
#endif
    // Heading: turned toward the motion (toward the player while attacking) by at most a substep's turn.
    float speed = sqrt(m.z * m.z + m.w * m.w);
    bool attacking = c.x == ATTACK;
    vec2 goal = attacking ? s.zw : m.zw;
    float glen = attacking ? sqrt(s.z * s.z + s.w * s.w) : speed;
    bool turning = glen > 0.05 && c.x < DYING;
    vec2 h0 = hd.xy;
    vec4 w = locomotion_weights(k, speed, tr.y, tr.x);
    if (turning) {
        vec2 u = goal * (1.0 / (glen + 1e-30));
        if (hd.x * u.x + hd.y * u.y >= u_cos_step) {
            hd.xy = u;
        } else {
            float sn = hd.x * u.y - hd.y * u.x >= 0.0 ? -u_sin_step : u_sin_step;
            hd.xy = vec2(u_cos_step * h0.x + sn * h0.y, u_cos_step * h0.y - sn * h0.x);
        }
        if (u_plant_feet && c.y == NO_ACTION && hd.xy != h0 && k.more.w > 0.0) {  // about the planted foot
            m.xy = clamp(m.xy + pivot_shift(c.w, hd.z, w.xyz, h0, hd.xy, hd.w), -u_half, u_half);
#ifdef TOWN
            m.xy = keep_out(m.xy, u_half);  // (a pivot by a wall must not step into it)
#endif
        }
    }
    // The locomotion phase: speed over the blended stride, for the share of the motion along the heading.
    float forward = clamp((m.z * hd.x + m.w * hd.y) / max(speed, 1e-12), 0.0, 1.0);
    float rate = phase_rate(k, speed, tr.y, w.w, hd.w) * (speed > 0.0 ? forward : 1.0);
    hd.z = advance_phase(hd.z, rate * u_h);
    motion_[i] = m;
    heading_[i] = hd;
}
#endif
