#version 330 core
// Ground plane y = 0 around the camera. Positions arrive camera-relative; u_origin is the world
// position of the camera modulo the grid period, so the grid stays still while the camera moves.
in vec2 in_position;
#include "frame.glsl"
uniform vec3 u_eye;        // camera position relative to the ground-grid origin (small numbers)
out vec3 v_world;
out vec2 v_grid;
void main() {
    vec3 world = vec3(in_position.x, -u_eye.y, in_position.y);
    v_world = world;
    v_grid = in_position + u_eye.xz;
    gl_Position = u_camera_view_proj * vec4(world, 1.0);
}
