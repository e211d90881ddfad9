#version 330 core
#if !defined(DEPTH_ONLY) && defined(GL_ARB_conservative_depth)
#extension GL_ARB_conservative_depth : enable
#endif
// Impostors (impostor.vert.glsl): the four atlas cells blended (two views by two frames), weighted by
// their coverage; a texel less than half covered is left out. The colour pass lights the atlas's albedo
// and normal as skin.frag.glsl lights a mesh (the same sun, sky, shadows and fog, the agent's tint), and
// writes the depth the atlas holds, so impostors and meshes intersect; the shadow pass (DEPTH_ONLY) keeps
// the coverage only.
#include "impostor_sample.glsl"
flat in ivec4 v_cells;
flat in vec2 v_blend;
in vec2 v_corner;
#ifndef DEPTH_ONLY
#include "lighting.glsl"
#include "octahedral.glsl"
#include "vertex_packing.glsl"
in vec3 v_world;
flat in vec3 v_toward;
flat in float v_depth_range;
flat in vec2 v_heading;
flat in vec4 v_tint;
flat in uint v_fade;
#include "lod_fade.glsl"
out vec4 o_color;
#ifdef GL_ARB_conservative_depth
layout(depth_greater) out float gl_FragDepth;  // the quad lies nearer than the atlas's depths: the depth test stays early
#endif
#endif

// The bake cleared every texel no triangle covers to 0, so a filtered texel is already weighted by its
// coverage (the depth's two channels decode linearly): sums over the cells, divided by the coverage.
void main() {
#ifndef DEPTH_ONLY
    if (faded_out(v_fade, gl_FragCoord.xy)) discard;
#endif
    vec4 w = vec4((1.0 - v_blend.x) * (1.0 - v_blend.y), v_blend.x * (1.0 - v_blend.y), (1.0 - v_blend.x) * v_blend.y, v_blend.x * v_blend.y);
    vec4 albedo = vec4(0.0);
#ifndef DEPTH_ONLY
    vec2 oct = vec2(0.0);
    float depth = 0.0;
#endif
    for (int k = 0; k < 4; ++k) {
        if (w[k] <= 0.0) continue;
        vec3 at = cell_coord(v_cells[k], v_corner);
        albedo += w[k] * textureLod(u_atlas_albedo, at, 0.0);
#ifndef DEPTH_ONLY
        vec4 nd = textureLod(u_atlas_normal_depth, at, 0.0);
        oct += w[k] * nd.xy;
        depth += w[k] * atlas_depth(nd);
#endif
    }
    if (albedo.a < 0.5) discard;
#ifndef DEPTH_ONLY
    vec3 n = turn_about_y(v_heading, oct_decode(oct / albedo.a * 2.0 - 1.0));
    vec3 world = atlas_surface(v_world, v_toward, depth / albedo.a, v_depth_range);
    gl_FragDepth = window_depth(u_camera_view_proj, world);
#ifdef UNLIT
    o_color = vec4(shade_unlit(albedo.rgb / albedo.a * v_tint.rgb, world), 1.0);  // a KHR_materials_unlit character's
#else
    o_color = vec4(shade(albedo.rgb / albedo.a * v_tint.rgb, world, n), 1.0);
#endif
#endif
}
