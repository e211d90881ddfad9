#version 410 core
// Counting one list (crowd/draw/feedback_cull.py): glDrawTransformFeedbackStream draws one point per record
// its stream wrote (the count never leaves the GPU), each added as 1.0 into a texel of the list's block
// of the counts texture (feedback_count.frag.glsl, additive blending). Points blended into one texel
// wait for one another, so they are spread over the block's u_count_block^2 texels.
uniform ivec2 u_count_texel;  // the block's first texel
uniform int u_count_block;    // its side, a power of two
uniform vec2 u_count_size;    // the counts texture's size, in texels

void main() {
    int id = gl_VertexID;
    vec2 texel = vec2(u_count_texel + ivec2(id & (u_count_block - 1), (id / u_count_block) & (u_count_block - 1)));
    gl_Position = vec4((texel + 0.5) / u_count_size * 2.0 - 1.0, 0.0, 1.0);
}
