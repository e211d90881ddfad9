// What the transform-feedback cull decides for one agent (crowd/draw/feedback_cull.py): the compute cull's
// pick (lod_pick.glsl) for the one character a draw covers, in the same float32 steps, so both GPU paths list
// the same agents, and the volumes it tests against. Used by feedback_cull.vert.glsl (the lists),
// feedback_visible.vert.glsl (each agent's visibility, for the weapons) and feedback_census.vert.glsl (the
// stats). STEPS (a define): the most LOD switch distances a character of the cast has.
#include "lod_pick.glsl"
uniform vec4 u_bound;       // the character's bind pose sphere: xyz its centre, w its radius (times the agent's scale)
uniform float u_lod_start[STEPS];  // its LOD switch distances, ascending
uniform int u_lod_steps;
uniform int u_lod_count;    // the character's mesh LODs
uniform float u_impostor_start;  // metres from which its agents are its impostor, LOD u_lod_count (3e38: never)
uniform float u_lod_fade;   // metres past each LOD switch over which both LODs are drawn (0: none)
uniform int u_culling;

Pick pick(vec4 position_scale, vec4 planes[6], float reach, int lod_bias) {
    vec3 center = position_scale.xyz + u_bound.xyz * position_scale.w;
    float radius = u_bound.w * position_scale.w;
    bool inside = true;
    if (u_culling != 0) {
        for (int k = 0; k < 6; ++k) inside = inside && dot(planes[k].xyz, center) + planes[k].w >= -radius;
        inside = inside && length(center) - radius <= reach;
    }
    float dist = length(center);
    int passed = 0;
    float last = -1.0;
    for (int k = 0; k < u_lod_steps; ++k) {
        if (dist >= u_lod_start[k]) {
            passed += 1;
            last = u_lod_start[k];
        }
    }
    return lod_pick(inside, dist, passed, last, u_lod_count, u_impostor_start, u_lod_fade, lod_bias);
}

// The volumes a frame culls against: the view, and each shadow cascade's box (culled one LOD coarser,
// and no farther from the eye than its reach).
uniform vec4 u_planes[6];          // the view's; inside: dot(n, p) + d >= 0 (camera-relative)
uniform int u_cascades;
uniform vec4 u_shadow_planes[12];  // cascade k's at 6 k
uniform float u_shadow_reach[2];   // metres from the eye past which an agent casts nothing into cascade k

Pick view_pick(vec4 position_scale) {
    return pick(position_scale, u_planes, 3.0e38, 0);
}

Pick cascade_pick(vec4 position_scale, int k) {
    vec4 planes[6];
    for (int i = 0; i < 6; ++i) planes[i] = u_shadow_planes[6 * k + i];
    return pick(position_scale, planes, u_shadow_reach[k], 1);
}
