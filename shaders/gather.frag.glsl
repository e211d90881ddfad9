#version 330 core
// Readback gather: copies the socket joints of armed agents out of the palette into one compact
// texture, so the CPU reads 48 bytes per weapon instead of the whole palette. Entry e sits at
// (3 * (e % ENTRIES_PER_ROW) + plane, e / ENTRIES_PER_ROW): the three rows of its skinning matrix side
// by side, so the target read row by row is the entries' (3, 4) matrices one after the other.
uniform usampler2D u_entries;  // per entry: the palette texel code of the socket joint (palette.glsl)
#include "palette.glsl"
out vec4 o_row;

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    int column = p.x / 3;
    int plane = p.x - 3 * column;
    uint t = texelFetch(u_entries, ivec2(column, p.y), 0).r;
    ivec3 texel = palette_texel(t);
    // A copy, bit for bit: the weapon must use exactly the matrix the body is skinned with.
    if (plane == 0) {
        o_row = texelFetch(u_palette0, texel, 0);
    } else if (plane == 1) {
        o_row = texelFetch(u_palette1, texel, 0);
    } else {
        o_row = texelFetch(u_palette2, texel, 0);
    }
}
