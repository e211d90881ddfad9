#version 410 core
// The first half of turning counts into commands (crowd/draw/feedback_cull.py): texel (b, y) sums row y of
// block b of the counts texture, so the commands pass adds COUNT_BLOCK sums a block instead of
// COUNT_BLOCK^2 texels. The counts are whole numbers below 2^24 a texel, exact in float32.
uniform sampler2D u_counts;
uniform int u_count_block;

out uint partial;

void main() {
    ivec2 at = ivec2(gl_FragCoord.xy);
    uint sum = 0u;
    for (int i = 0; i < u_count_block; ++i) sum += uint(texelFetch(u_counts, ivec2(at.x * u_count_block + i, at.y), 0).r + 0.5);
    partial = sum;
}
