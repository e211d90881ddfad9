#version 410 core
// One triangle over the whole target (no vertex buffer): feedback_commands.frag.glsl runs once per texel.
void main() {
    gl_Position = vec4(float((gl_VertexID & 1) * 4 - 1), float((gl_VertexID & 2) * 2 - 1), 0.0, 1.0);
}
