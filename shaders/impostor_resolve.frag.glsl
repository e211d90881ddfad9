#version 430
// The splatted impostors' pixels (impostor_splat.comp.glsl) written into the frame with their depth, so
// the depth test sets them among the meshes, quads and ground like any fragment.
layout(std430, binding = 2) readonly buffer Depths { uint splat_depth[]; };
layout(std430, binding = 4) readonly buffer Colours { uint splat_colour[]; };
uniform ivec2 u_size;
out vec4 o_color;

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    int pixel = p.y * u_size.x + p.x;
    uint depth = splat_depth[pixel];
    if (depth == 0xFFFFFFFFu) discard;
    o_color = unpackUnorm4x8(splat_colour[pixel]);
    gl_FragDepth = uintBitsToFloat(depth);
}
