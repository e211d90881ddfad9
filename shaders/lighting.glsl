// Shared lighting for the crowd and the ground: a low sun with soft shadows, a cool sky and warm
// ground bounce, a rim light so silhouettes read against the ground, and distance fog.
#include "frame.glsl"
#ifdef SHADOWS
// CASCADES tiles side by side in one depth texture (crowd/draw/shadows.py): a fragment takes the
// first cascade whose tile holds it, with its PCF kernel inside the tile.
uniform sampler2DShadow u_shadow_map;  // (the cascades' matrices, texels and biases: frame.glsl)
#endif

float sun_visibility(vec3 world, vec3 n) {
#ifdef SHADOWS
    float tile = 1.0 / float(CASCADES);
    vec2 texel = 1.0 / vec2(textureSize(u_shadow_map, 0));
    for (int k = 0; k < CASCADES; ++k) {
        // Offset along the normal by 1.5 texels of this cascade against acne, then a PCF of four
        // filtered taps half a texel off each way (each tap compares 2x2 texels: a tent over 3x3).
        vec4 l = u_light_view_proj[k] * vec4(world + n * (1.5 * u_cascade[k].x), 1.0);
        vec3 uvz = l.xyz / l.w * 0.5 + 0.5;
        float edge = 2.0 * texel.y;  // the kernel's reach, in tile units (tiles are square)
        if (any(lessThan(uvz, vec3(edge, edge, 0.0))) || any(greaterThan(uvz, vec3(1.0 - edge, 1.0 - edge, 1.0)))) continue;
        vec2 uv = vec2((uvz.x + float(k)) * tile, uvz.y);
        float z = uvz.z - u_cascade[k].y;
        float lit = texture(u_shadow_map, vec3(uv + vec2(-0.5, -0.5) * texel, z)) + texture(u_shadow_map, vec3(uv + vec2(0.5, -0.5) * texel, z))
                  + texture(u_shadow_map, vec3(uv + vec2(-0.5, 0.5) * texel, z)) + texture(u_shadow_map, vec3(uv + vec2(0.5, 0.5) * texel, z));
        return lit * 0.25;
    }
    return 1.0;
#else
    return 1.0;
#endif
}

// A colour as it reaches the display through the fog: an unlit surface's albedo (KHR_materials_unlit),
// or a lit one's light.
vec3 shade_unlit(vec3 color, vec3 world) {
    float fog = 1.0 - exp(-u_fog.a * length(world));
    color = mix(color, u_fog.rgb, clamp(fog, 0.0, 1.0));
    return pow(max(color, vec3(0.0)), vec3(1.0 / 2.2));  // linear → display
}

vec3 shade(vec3 albedo, vec3 world, vec3 n) {
    vec3 view = normalize(-world);  // the camera is at the origin
    float ndl = max(dot(n, u_sun_dir.xyz), 0.0);
    vec3 ambient = mix(u_ground_color.rgb, u_sky_color.rgb, 0.5 + 0.5 * n.y);
    float rim = pow(1.0 - max(dot(n, view), 0.0), 3.0) * 0.35;
    return shade_unlit(albedo * (ambient + u_sun_color.rgb * ndl * sun_visibility(world, n)) + rim * u_sky_color.rgb, world);
}
