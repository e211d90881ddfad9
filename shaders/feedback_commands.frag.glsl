#version 410 core
// The indirect draw commands of the transform-feedback cull (crowd/draw/feedback_cull.py), one
// DrawElementsIndirectCommand per row of 5 texels, which glReadPixels then packs into the command buffer
// on the GPU (nothing waits): count (the draw's indices), instanceCount (its list's counted records), and
// zeros (GL 4.1 reads no baseInstance: each list is a buffer of its own). The rows after the commands
// hold u_stats more counts, of the blocks from u_stats_first on (the stats' agents per LOD).
uniform usampler2D u_partials;    // (blocks, COUNT_BLOCK): feedback_partial.frag.glsl's row sums of each block
uniform usampler2D u_draw_table;  // (rows, 1): r a command's index count, g its list's block
uniform int u_count_block;
uniform int u_rows;               // command rows
uniform int u_stats_first;
uniform int u_stats;

out uint word;

uint counted(int block) {
    uint sum = 0u;
    for (int i = 0; i < u_count_block; ++i) sum += texelFetch(u_partials, ivec2(block, i), 0).r;
    return sum;
}

void main() {
    ivec2 at = ivec2(gl_FragCoord.xy);
    word = 0u;
    if (at.y >= u_rows) {
        int stat = (at.y - u_rows) * 5 + at.x;
        if (stat < u_stats) word = counted(u_stats_first + stat);
        return;
    }
    uvec2 draw = texelFetch(u_draw_table, ivec2(at.y, 0), 0).rg;
    if (at.x == 0) word = draw.r;
    else if (at.x == 1) word = counted(int(draw.g));
}
