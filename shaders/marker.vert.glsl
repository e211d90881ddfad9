#version 330 core
// Ground markers (the player, the selected agent): a flat ring per instance, a few centimetres above
// the ground so it is not lost in it. Positions arrive camera-relative.
in vec2 in_ring;            // x: angle (radians), y: 0 inner edge, 1 outer edge
in vec4 i_position_radius;  // ring centre relative to the camera, outer radius
in vec4 i_color;
uniform mat4 u_view_proj;
out vec4 v_color;
void main() {
    float r = i_position_radius.w * mix(0.78, 1.0, in_ring.y);
    vec3 world = i_position_radius.xyz + vec3(cos(in_ring.x) * r, 0.03, sin(in_ring.x) * r);
    v_color = i_color;
    gl_Position = u_view_proj * vec4(world, 1.0);
}
