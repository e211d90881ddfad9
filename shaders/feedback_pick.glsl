// What the transform-feedback cull decides for one agent (crowd/draw/feedback_cull.py): the compute
// cull's agent_draws (cull_common.glsl) for the one character a draw covers, in the same float32 steps,
// so both GPU paths list the same agents, and the volumes it tests against. Used by feedback_cull.vert.glsl (the lists),
// feedback_visible.vert.glsl (each agent's visibility, for the weapons) and feedback_census.vert.glsl (the stats).
uniform vec4 u_bound;       // the character's bind pose sphere: xyz its centre, w its radius (times the agent's scale)
uniform float u_lod_start[4];
uniform int u_lod_steps;
uniform int u_lod_count;    // the character's mesh LODs
uniform float u_impostor_start;  // metres from which its agents are its impostor, LOD u_lod_count (3e38: never)
uniform float u_lod_fade;   // metres past each LOD switch over which both LODs are drawn (0: none)
uniform int u_culling;

struct Pick {
    bool inside;    // in the volume (always, with culling off)
    int lod;        // the LOD it is drawn at (u_lod_count: its impostor)
    int finer;      // across a fade, the LOD it is leaving
    bool fading;    // within u_lod_fade past the switch behind it (never with a LOD bias: shadows)
    bool held;      // drawn as its impostor alone, which holds its weapon itself
    uint through;   // how far through the fade band, 0 to 127
};

Pick pick(vec4 position_scale, vec4 planes[6], float margin, float reach, int lod_bias) {
    Pick p;
    vec3 center = position_scale.xyz + u_bound.xyz * position_scale.w;
    float radius = u_bound.w * position_scale.w + margin;
    p.inside = true;
    if (u_culling != 0) {
        for (int k = 0; k < 6; ++k) p.inside = p.inside && dot(planes[k].xyz, center) + planes[k].w >= -radius;
        p.inside = p.inside && length(center) - radius <= reach;
    }
    float dist = length(center);
    int lod = 0;
    for (int k = 0; k < u_lod_steps; ++k) lod += int(dist >= u_lod_start[k]);
    int mesh_lod = min(lod + lod_bias, u_lod_count - 1);
    bool impostor = dist >= u_impostor_start;
    float boundary = impostor ? u_impostor_start : (lod > 0 ? u_lod_start[lod - 1] : -1.0);
    p.finer = impostor ? mesh_lod : min(lod - 1, u_lod_count - 1);
    p.lod = impostor ? u_lod_count : mesh_lod;
    p.fading = u_lod_fade > 0.0 && lod_bias == 0 && boundary >= 0.0 && dist < boundary + u_lod_fade && p.finer != p.lod;
    p.held = impostor && !p.fading;
    p.through = p.fading ? uint(clamp((dist - boundary) / u_lod_fade, 0.0, 1.0) * 127.0 + 0.5) : 0u;
    return p;
}

// The volumes a frame culls against: the view, and each shadow cascade's box (culled one LOD coarser,
// and no farther from the eye than its reach).
uniform vec4 u_planes[6];          // the view's; inside: dot(n, p) + d >= 0 (camera-relative)
uniform int u_cascades;
uniform vec4 u_shadow_planes[12];  // cascade k's at 6 k
uniform float u_shadow_reach[2];   // metres from the eye past which an agent casts nothing into cascade k

Pick view_pick(vec4 position_scale) {
    return pick(position_scale, u_planes, 0.0, 3.0e38, 0);
}

Pick cascade_pick(vec4 position_scale, int k) {
    vec4 planes[6];
    for (int i = 0; i < 6; ++i) planes[i] = u_shadow_planes[6 * k + i];
    return pick(position_scale, planes, 0.0, u_shadow_reach[k], 1);
}
