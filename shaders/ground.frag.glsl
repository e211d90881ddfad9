#version 330 core
#include "lighting.glsl"
in vec3 v_world;
in vec2 v_grid;
out vec4 o_color;
#ifdef TOWN
// The town's ground (crowd/asset/town.py): v_grid is the world position modulo TILE, so a block's
// corner, on a street crossing, is at 0. Streets STREET wide around each block, with a dashed centre
// line; sidewalks SIDEWALK wide inside them, in slabs; the lot's paving inside those.
uniform float u_tile;
uniform float u_street;
uniform float u_sidewalk;

vec3 town_ground() {
    vec2 t = mod(v_grid, u_tile);
    vec2 edge = min(t, u_tile - t);  // metres from the nearest street centre line, per axis
    float centre = min(edge.x, edge.y);
    vec2 px = fwidth(v_grid);
    if (centre < 0.5 * u_street) {  // a street: asphalt, and the centre line of the street this point is in
        bool along_z = edge.x < edge.y;  // in the street that runs along z (its centre line is x = k * tile)
        float across = along_z ? edge.x : edge.y;
        float along = along_z ? t.y : t.x;
        float dash = step(0.5, fract(along / 3.0)) * step(0.5 * u_street + 2.0, along_z ? edge.y : edge.x);  // not in the crossing
        float line = (1.0 - smoothstep(0.08, 0.08 + max(px.x, px.y), across)) * dash;
        return mix(vec3(0.055, 0.055, 0.06), vec3(0.5, 0.42, 0.12), line);
    }
    vec2 slab = abs(fract(v_grid / 1.5 - 0.5) - 0.5) * 1.5 / max(px, vec2(1e-4));
    float joint = 1.0 - min(min(slab.x, slab.y), 1.0);
    if (centre < 0.5 * u_street + u_sidewalk) return mix(vec3(0.26, 0.255, 0.24), vec3(0.17, 0.165, 0.16), joint * 0.6);
    return vec3(0.12, 0.115, 0.105);
}
#endif

void main() {
#ifdef TOWN
    vec3 albedo = town_ground();
#else
    // 1 m grid lines, antialiased by the screen-space derivative.
    vec2 g = abs(fract(v_grid - 0.5) - 0.5) / fwidth(v_grid);
    float line = 1.0 - min(min(g.x, g.y), 1.0);
    vec3 albedo = mix(vec3(0.13, 0.13, 0.11), vec3(0.2, 0.2, 0.17), line * 0.7);
#endif
    o_color = vec4(shade(albedo, v_world, vec3(0.0, 1.0, 0.0)), 1.0);
}
