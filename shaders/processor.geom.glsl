#version 330 core
// Animation processor, GL 3.3 path: sends each quad to its texture layer of the palette (gl_Layer, a
// geometry shader's output since GL 3.2), so a palette taller than one texture may hold spans layers.
layout(triangles) in;
layout(triangle_strip, max_vertices = 3) out;
in int v_layer[];
flat out int g_layer;        // the layer within the ring slot
uniform int u_first_layer;   // the slot's first layer

void main() {
    for (int i = 0; i < 3; ++i) {
        gl_Position = gl_in[i].gl_Position;
        gl_Layer = u_first_layer + v_layer[i];
        g_layer = v_layer[i];
        EmitVertex();
    }
    EndPrimitive();
}
