#version 330 core
// crowd-bench fragment: the floor of any fragment pass over the palette's texels: no sampling and no
// arithmetic, constants into the same RGBA32F targets the processor writes (TARGETS of them).
layout(location = 0) out vec4 o_row0;
#if TARGETS == 3
layout(location = 1) out vec4 o_row1;
layout(location = 2) out vec4 o_row2;
#endif
flat in int g_layer;

void main() {
    o_row0 = vec4(gl_FragCoord.xy, 1.0, 2.0);
#if TARGETS == 3
    o_row1 = o_row0 * 2.0;
    o_row2 = o_row0 * 3.0;
#endif
}
