#version 330 core
// The town (crowd/draw/town.py): buildings, cars, barriers and kerbs, one instanced draw per mesh. An
// instance is a placement on the ground: its origin relative to the camera (float64 on the CPU, then
// float32, as the crowd's; on the GPU cull path relative to the districts' anchor, u_anchor_rel added) and its heading, which turns the mesh's +Z toward (sin, 0, cos) as an agent's
// does; its tint multiplies the vertex colours. Shares skin.frag.glsl and depth.frag.glsl with the crowd.
//
// Defines: DEPTH_ONLY (shadow pass: position only).

in vec3 in_position;
in uvec2 in_packed;     // x: normal, snorm10 x3 | y: colour, RGBA8
in vec3 i_position;     // the placement's origin, relative to the camera
in uvec2 i_fields;      // x: cos, sin of the heading, snorm16 x2 | y: tint, RGBA8

#ifdef DEPTH_ONLY
uniform mat4 u_view_proj;  // the shadow cascade's, camera-relative
#else
#include "frame.glsl"
#define u_view_proj u_camera_view_proj
#endif
uniform vec3 u_anchor_rel;  // where i_position counts from, relative to the camera (0: i_position is camera-relative)

#ifndef DEPTH_ONLY
out vec3 v_world;
out vec3 v_normal;
out vec4 v_color;
#endif

#include "vertex_packing.glsl"

void main() {
    vec2 heading = heading_cos_sin(i_fields.x);
    vec3 world = (u_anchor_rel + i_position) + turn_about_y(heading, in_position);
    gl_Position = u_view_proj * vec4(world, 1.0);
#ifndef DEPTH_ONLY
    v_world = world;
    v_normal = turn_about_y(heading, unpack_normal(in_packed.x));
    v_color = unpack_rgba8(in_packed.y) * unpack_rgba8(i_fields.y);
#endif
}
