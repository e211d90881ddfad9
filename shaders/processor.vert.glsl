#version 330 core
// Animation processor, GL 3.3 path: quads covering the palette texels that hold agents, one set per
// texture layer of the ring slot this run writes. Positions arrive in normalised device coordinates
// of one layer; z is the layer within the slot.
in vec3 in_position;
out int v_layer;
void main() {
    gl_Position = vec4(in_position.xy, 0.0, 1.0);
    v_layer = int(in_position.z);
}
