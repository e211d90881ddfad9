// crowd.sim.locomotion's arithmetic for one agent of character k.
vec4 locomotion_weights(Kind k, float speed, float walk, float speed_factor) {  // idle, walk, run, run share
    float to_walk = min(speed / (k.loco.w * walk), 1.0);
    float run_t = clamp((speed - walk) / (k.loco.z * speed_factor - walk), 0.0, 1.0);
    return vec4(1.0 - to_walk, to_walk * (1.0 - run_t), to_walk * run_t, run_t);
}

float blended_stride(Kind k, float run_t, float scale) {
    return (k.loco.x + run_t * (k.loco.y - k.loco.x)) * scale;
}

float phase_rate(Kind k, float speed, float walk, float run_t, float scale) {
    float moving = max(speed, k.loco.w * walk) / blended_stride(k, run_t, scale);
    return speed > 0.0 ? moving : 1.0 / max(k.more.x, 1e-3);
}

float advance_phase(float phase, float step) {
    float p = phase + step;
    p -= floor(p);
    return p < 1.0 ? p : 0.0;  // (a tiny negative phase wraps to 1 - 1e-8, which rounds to 1: the same pose as 0)
}
