#version 330 core
// Preview of CPU-skinned positions (the float64 reference does the skinning): a debugging view,
// not the crowd renderer.
uniform mat4 u_view_proj;
in vec3 in_position;
in vec3 in_normal;
in vec4 in_color;
out vec3 v_normal;
out vec4 v_color;
void main() {
    v_normal = in_normal;
    v_color = in_color;
    gl_Position = u_view_proj * vec4(in_position, 1.0);
}
