#version 330 core
// Weapons: one instanced draw per weapon mesh. Each instance is the weapon's model matrix, computed on
// the CPU from the socket matrix it read back (agent world x socket x inverse grip), relative to the
// camera like everything else. Shares skin.frag.glsl and depth.frag.glsl with the crowd.
//
// Defines: DEPTH_ONLY (shadow pass: position only).

in vec3 in_position;
in uvec2 in_packed;  // x: normal, snorm10 x3 | y: colour, RGBA8

in vec4 i_row0;  // rows of the camera-relative 3x4 model matrix
in vec4 i_row1;
in vec4 i_row2;

uniform mat4 u_view_proj;

#ifndef DEPTH_ONLY
out vec3 v_world;
out vec3 v_normal;
out vec4 v_color;
#endif

void main() {
    vec4 p = vec4(in_position, 1.0);
    vec3 world = vec3(dot(i_row0, p), dot(i_row1, p), dot(i_row2, p));
    gl_Position = u_view_proj * vec4(world, 1.0);
#ifndef DEPTH_ONLY
    vec3 n = vec3(ivec3(uvec3(in_packed.x) << uvec3(22u, 12u, 2u)) >> 22) / 511.0;
    v_world = world;
    v_normal = vec3(dot(i_row0.xyz, n), dot(i_row1.xyz, n), dot(i_row2.xyz, n));
    v_color = vec4((uvec4(in_packed.y) >> uvec4(0u, 8u, 16u, 24u)) & 0xFFu) / 255.0;
#endif
}
