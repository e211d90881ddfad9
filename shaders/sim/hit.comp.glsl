#version 430
// The player's blows on the GPU (the numpy twin: crowd.sim.ai.CrowdAI.hit): HIT_LIST hits the agents
// of a list (distinct numbers); NEAREST_D / NEAREST_I find the nearest living agent within reach of a
// point (the lowest number among equals: the same agent whatever order threads arrive in), and
// HIT_NEAREST hits it (LOOK_AT notes where it stands instead: what a survivor looks at); SWEEP hits
// every living agent within reach on the side a swing faces. COUNT counts the states for the HUD.
layout(local_size_x = 256) in;
#include "sim/agents.glsl"
layout(std430, binding = 9) buffer Targets { int targets_[]; };

uniform int u_n;
uniform int u_count;    // HIT_LIST: agents in the list
uniform vec2 u_point;   // relative to the origin
uniform float u_reach;
uniform vec2 u_front;
uniform int u_search;   // NEAREST_D / NEAREST_I: 0 a strike's search, 1 a look's
uniform int u_selected; // COUNT: the agent whose row is copied out (-1: none)
uniform vec3 u_ray_origin, u_ray_dir;   // PICK_T / PICK_I: a ray (relative to the origin), and each agent's upright
uniform float u_pick_radius, u_pick_height;  // cylinder, radius and height times its scale

void hit(int i) {
    ivec4 c = codes_[i];
    if (c.x >= DYING) return;
    Kind k = kinds[c.w];
    if (k.roles.z >= 0.0) c.z -= 1;  // without a death clip, a zombie does not die
    vec4 t = timers_[i];
    if (c.z <= 0) {
        c.x = DYING;
        c.y = ACT_DEATH;
        t.x = 0.0;
        t.y = 0.0;
        atomicAdd(kills, 1u);
    } else {
        if (k.roles.y >= 0.0) {
            c.x = HIT;
            c.y = ACT_HIT;
            t.x = 0.0;
            t.y = 0.0;
        }
        t.w = max(t.w, goal_[i].w);  // a hit agent knows where the player is
        atomicAdd(hurt, 1u);
    }
    codes_[i] = c;
    timers_[i] = t;
}

float distance_to_point(int i) {
    vec2 d = motion_[i].xy - u_point;
    return sqrt(d.x * d.x + d.y * d.y);
}

void main() {
    int i = int(gl_GlobalInvocationID.x);
#ifdef HIT_LIST
    if (i < u_count) hit(targets_[i]);
#endif
#ifdef NEAREST_D
    if (i < u_n && codes_[i].x < DYING) {
        float d = distance_to_point(i);
        if (d <= u_reach) atomicMin(nearest_d[u_search], floatBitsToUint(d));
    }
#endif
#ifdef NEAREST_I
    if (i < u_n && codes_[i].x < DYING && floatBitsToUint(distance_to_point(i)) == nearest_d[u_search]) atomicMin(nearest_i[u_search], uint(i));
#endif
#ifdef HIT_NEAREST
    if (i == 0 && nearest_i[0] < uint(u_n)) hit(int(nearest_i[0]));
#endif
#ifdef LOOK_AT
    if (i == 0 && nearest_i[1] < uint(u_n)) nearest_at = motion_[nearest_i[1]].xy;
#endif
#ifdef SWEEP
    if (i < u_n && codes_[i].x < DYING) {
        vec2 d = motion_[i].xy - u_point;
        if (d.x * d.x + d.y * d.y <= u_reach * u_reach && d.x * u_front.x + d.y * u_front.y >= 0.0) hit(i);
    }
#endif
#if defined(PICK_T) || defined(PICK_I)
    if (i < u_n) {  // the ray against the agent's upright cylinder, solved in the ground plane (the numpy twin: CrowdSession.pick)
        vec4 m = motion_[i];
        float scale = heading_[i].w;
        vec2 o = u_ray_origin.xz - m.xy, d = u_ray_dir.xz;
        float radius = u_pick_radius * scale;
        float a = dot(d, d), b = dot(o, d), c = dot(o, o) - radius * radius;
        float disc = b * b - a * c;
        if (disc >= 0.0 && a > 1e-12) {
            float t = (-b - sqrt(max(disc, 0.0))) / a;
            float y = u_ray_origin.y + t * u_ray_dir.y;
            if (t > 0.0 && y >= 0.0 && y <= u_pick_height * scale) {
#ifdef PICK_T
                atomicMin(pick_t, floatBitsToUint(t));
#else
                if (floatBitsToUint(t) == pick_t) atomicMin(picked, uint(i));
#endif
            }
        }
    }
#endif
#ifdef COUNT
    if (i < u_n) {
        int state = codes_[i].x;
        atomicAdd(state_count[state], 1u);
        if (state < DYING && distance_to_point(i) < u_reach) atomicAdd(near, 1u);
    }
    if (i == 0) {
        selected = u_selected >= 0 && u_selected < u_n ? u_selected : -1;
        if (selected >= 0) {
            selected_motion = motion_[selected];
            selected_heading = heading_[selected];
            selected_codes = codes_[selected];
        }
    }
#endif
}
