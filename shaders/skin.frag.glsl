#version 330 core
// Shared by the crowd, the weapons and the Panda3D peer of crowd-bench peers (panda_actor.vert.glsl).
// TEXTURED: the base colour times a layer of one of the crowd's texture arrays (crowd/draw/materials.py).
#include "lighting.glsl"
in vec3 v_world;
in vec3 v_normal;
in vec4 v_color;
#ifdef TEXTURED
in vec2 v_uv;
uniform sampler2DArray u_albedo;  // sRGB BC1 or linear RGBA16F, read as linear light; wrap and filter from the piece's sampler object
uniform sampler2DArray u_albedo_coarse;  // a BC1 array's coarser mip levels in RGBA16F, the same layers
uniform float u_coarse_lod;       // the level of detail from which u_albedo_coarse is read (1e9: never)
uniform vec2 u_albedo_size;       // u_albedo's texels, for the level of detail
uniform float u_layer;
uniform vec2 u_uv_mirror;         // 1 where the wrap is MIRRORED_REPEAT (the sampler itself repeats)
#endif
layout(location = 0) out vec4 o_color;
#ifdef LOD_FADE
#include "lod_fade.glsl"
flat in uint v_fade;
#endif
#ifdef UNLIT_PIECES
flat in uint v_unlit;  // 1: the piece's material is KHR_materials_unlit
#endif
#ifdef IMPOSTOR_BAKE
// The impostor atlas's cells (crowd/draw/impostors.py): the albedo before lighting and tint, then the
// model-space normal (octahedral) and the depth toward the camera as 16 bits in two channels.
#include "octahedral.glsl"
in float v_bake_depth;
layout(location = 1) out vec4 o_normal_depth;
#endif
void main() {
#ifdef LOD_FADE
    if (faded_out(v_fade, gl_FragCoord.xy)) discard;
#endif
    vec3 n = normalize(v_normal);
    if (!gl_FrontFacing) n = -n;
    vec3 albedo = v_color.rgb;
#ifdef TEXTURED
    // Fold mirrored axes by hand; the unfolded coordinate's derivatives keep the mip level smooth
    // across the fold.
    vec2 folded = mix(v_uv, 1.0 - abs(mod(v_uv, 2.0) - 1.0), u_uv_mirror);
    vec2 du = dFdx(v_uv), dv = dFdy(v_uv);
    vec3 at = vec3(folded, u_layer);
    // GL's level of detail (the longer footprint's log2); the coarse array's level 0 is level
    // u_coarse_lod, blended in over the level before it as trilinear filtering blends two levels.
    vec2 fx = du * u_albedo_size, fy = dv * u_albedo_size;
    float lod = 0.5 * log2(max(max(dot(fx, fx), dot(fy, fy)), 1e-20));
    float coarse = clamp(lod - u_coarse_lod + 1.0, 0.0, 1.0);
    vec3 texel = vec3(0.0);
    if (coarse < 1.0) texel = textureGrad(u_albedo, at, du, dv).rgb;
    if (coarse > 0.0) texel = mix(texel, textureGrad(u_albedo_coarse, at, du, dv).rgb, coarse);
    albedo *= texel;
#endif
#ifdef IMPOSTOR_BAKE
    o_color = vec4(albedo, 1.0);
    float depth = floor(clamp(v_bake_depth * 0.5 + 0.5, 0.0, 1.0) * 65535.0 + 0.5);
    o_normal_depth = vec4(oct_encode(n) * 0.5 + 0.5, floor(depth / 256.0) / 255.0, mod(depth, 256.0) / 255.0);
#elif defined(UNLIT_PIECES)
    o_color = vec4(v_unlit != 0u ? shade_unlit(albedo, v_world) : shade(albedo, v_world, n), 1.0);
#else
    o_color = vec4(shade(albedo, v_world, n), 1.0);
#endif
}
