// Reading the palette (crowd/anim/processor.py says its layout): three RGBA32F array textures, the
// rows of each 3x4 skinning matrix, u_palette_rows texture rows to a layer. A texel is addressed by a
// code x | y << 12 (x < 4096, y the palette row counted across layers, below 2^20), as the instance
// records and the read-back's entries carry it.
uniform sampler2DArray u_palette0;
uniform sampler2DArray u_palette1;
uniform sampler2DArray u_palette2;
uniform int u_palette_rows;

ivec3 palette_texel(uint code) {
    int y = int(code >> 12);
    int layer = y / u_palette_rows;
    return ivec3(int(code & 0xFFFu), y - layer * u_palette_rows, layer);
}
