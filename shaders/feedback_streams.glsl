// The main of the transform-feedback culls' geometry shaders (feedback_cull.geom.glsl, the bodies';
// weapon_feedback.geom.glsl, the weapons'): each declares one output block a vertex stream, s0 to s3, and
// EMIT(block, stream), which writes the point's record into the block and emits it on that stream where
// the point is in that stream's list.
void main() {
    EMIT(s0, 0)
    EMIT(s1, 1)
    EMIT(s2, 2)
    EMIT(s3, 3)
}
