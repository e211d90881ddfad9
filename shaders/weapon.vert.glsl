#version 330 core
// Weapons: one instanced draw per (weapon, LOD) mesh. Each instance is the weapon's model matrix in
// its agent's model space, computed on the CPU from the socket matrix it read back (socket x inverse
// grip), and the agent's transform as the body's instance record carries it, applied here with the
// expressions of skin.vert.glsl, so the weapon and the hand holding it round alike. Shares
// skin.frag.glsl and depth.frag.glsl with the crowd.
//
// Defines: DEPTH_ONLY (shadow pass: position only); UNLIT_PIECES (some prop is KHR_materials_unlit: each
// vertex says whether its prop is lit, as skin.vert.glsl's pieces do).

in vec3 in_position;
in uvec2 in_packed;  // x: normal, snorm10 x3 | y: colour, RGBA8

in vec4 i_row0;  // rows of the 3x4 model matrix in the agent's model space
in vec4 i_row1;
in vec4 i_row2;
in vec4 i_position_scale;  // the agent's origin relative to the camera, uniform scale (its instance record's)
in uint i_heading;         // cos, sin of the agent's heading, snorm16 x2 (its instance record's)

#ifdef DEPTH_ONLY
uniform mat4 u_view_proj;  // the shadow cascade's, camera-relative
#else
#include "frame.glsl"
#define u_view_proj u_camera_view_proj
#endif
#include "vertex_packing.glsl"

#ifndef DEPTH_ONLY
out vec3 v_world;
out vec3 v_normal;
out vec4 v_color;
#ifdef UNLIT_PIECES
flat out uint v_unlit;  // bit 30 of the packed normal (crowd.draw.packing.UNLIT_BIT)
#endif
#endif

void main() {
    vec4 p = vec4(in_position, 1.0);
    vec3 model = vec3(dot(i_row0, p), dot(i_row1, p), dot(i_row2, p));
    // Heading about +Y, then scale and position: skin.vert.glsl's expressions for the body.
    vec2 heading = heading_cos_sin(i_heading);
    vec3 world = i_position_scale.xyz + i_position_scale.w * turn_about_y(heading, model);
    gl_Position = u_view_proj * vec4(world, 1.0);
#ifndef DEPTH_ONLY
    vec3 n = unpack_normal(in_packed.x);
    vec3 normal = vec3(dot(i_row0.xyz, n), dot(i_row1.xyz, n), dot(i_row2.xyz, n));
    v_world = world;
    v_normal = turn_about_y(heading, normal);
    v_color = unpack_rgba8(in_packed.y);
#ifdef UNLIT_PIECES
    v_unlit = (in_packed.x >> 30u) & 1u;
#endif
#endif
}
