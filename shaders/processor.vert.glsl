#version 330 core
// Animation processor, GL 3.3 path: the quad (and the partial last row) covering the palette texels
// that hold agents. Positions arrive in normalised device coordinates.
in vec2 in_position;
void main() {
    gl_Position = vec4(in_position, 0.0, 1.0);
}
