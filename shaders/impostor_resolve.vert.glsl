#version 430
// One triangle over the viewport: the splat's pixels into the frame (impostor_resolve.frag.glsl).
void main() {
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
