#version 330 core
#include "lighting.glsl"
in vec3 v_world;
in vec2 v_grid;
out vec4 o_color;
void main() {
    // 1 m grid lines, antialiased by the screen-space derivative.
    vec2 g = abs(fract(v_grid - 0.5) - 0.5) / fwidth(v_grid);
    float line = 1.0 - min(min(g.x, g.y), 1.0);
    vec3 albedo = mix(vec3(0.13, 0.13, 0.11), vec3(0.2, 0.2, 0.17), line * 0.7);
    o_color = vec4(shade(albedo, v_world, vec3(0.0, 1.0, 0.0)), 1.0);
}
