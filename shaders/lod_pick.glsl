// The LOD an agent is drawn at, and whether it is in the fade band past the switch behind it: the rule of
// the compute cull (cull.comp.glsl) and the transform-feedback cull (feedback_pick.glsl), in the same
// float32 steps, which the numpy cull (crowd/draw/cpu_cull.py) follows in float64.
struct Pick {
    bool inside;    // in the volume (always, with culling off)
    int lod;        // the LOD it is drawn at (lod_count: its impostor)
    int finer;      // across a fade, the LOD it is leaving
    bool fading;    // within lod_fade past the switch behind it (never with a LOD bias: shadows)
    bool held;      // drawn as its impostor alone, which holds its weapon itself
    uint through;   // how far through the fade band, 0 to 127
};

// `passed`: the character's LOD switch distances at or below `dist`, the last of them `last_start`;
// `lod_bias` 1 for the shadow passes, one LOD coarser.
Pick lod_pick(bool inside, float dist, int passed, float last_start, int lod_count, float impostor_start, float lod_fade, int lod_bias) {
    Pick p;
    p.inside = inside;
    int mesh_lod = min(passed + lod_bias, lod_count - 1);
    bool impostor = dist >= impostor_start;
    float boundary = impostor ? impostor_start : (passed > 0 ? last_start : -1.0);
    p.finer = impostor ? mesh_lod : min(passed - 1, lod_count - 1);
    p.lod = impostor ? lod_count : mesh_lod;
    p.fading = lod_fade > 0.0 && lod_bias == 0 && boundary >= 0.0 && dist < boundary + lod_fade && p.finer != p.lod;
    p.held = impostor && !p.fading;
    p.through = p.fading ? uint(clamp((dist - boundary) / lod_fade, 0.0, 1.0) * 127.0 + 0.5) : 0u;
    return p;
}
