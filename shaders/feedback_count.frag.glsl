#version 410 core
// One counted record, added into its texel (feedback_count.vert.glsl, feedback_census.vert.glsl).
out float count;

void main() {
    count = 1.0;
}
