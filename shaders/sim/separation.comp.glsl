#version 430
// The GPU twin of crowd.sim.separation's push: each living agent gathers its neighbours from the grid
// (the three rows of three cells around its own, at most SEPARATION_CELL_CAP from each row, in the
// grid's order) and sums half of each overlap closer than the pair's separation radius (the mean of its
// two characters'), in that order; no agent moves more than half its own radius. The push is written beside the agent; FINISH adds it.
layout(local_size_x = 256) in;
#include "sim/agents.glsl"
layout(std430, binding = 10) buffer Cell { uint cell_[]; };
layout(std430, binding = 12) buffer First { uint first_[]; };
layout(std430, binding = 14) buffer Sorted { uint sorted_[]; };
layout(std430, binding = 16) buffer Payload { vec4 payload_[]; };  // each slot's agent's motion: x, z in .xy

uniform int u_n;
uniform int u_side;
uniform float u_radius[KINDS];  // each character's (crowd.sim.separation.kind_radii): a pair keeps their mean apart
uniform float u_gain;  // min(stiffness x h, 1)

uniform int u_cells;

void main() {
    // A thread a slot of the grid, in cell order, so that neighbouring threads read the same cells; the
    // dying and the dead are in no slot, and keep the zero push the think pass left them.
    uint slot = gl_GlobalInvocationID.x;
    if (slot >= first_[u_cells]) return;
    int i = int(sorted_[slot]);
    uint c = cell_[i];
    vec2 p = payload_[slot].xy;
    vec2 push = vec2(0.0);
    bool any = false;
#if KINDS > 1
    float own = u_radius[codes_[i].w];
#else
    float own = u_radius[0];
#endif
    for (int row = -1; row <= 1; row++) {
        uint middle = uint(int(c) + row * u_side);
        uint lo = first_[middle - 1u];
        uint hi = min(first_[middle + 2u], lo + uint(SEPARATION_CELL_CAP));
        for (uint e = lo; e < hi; e++) {
            if (e == slot) continue;
            vec2 d = p - payload_[e].xy;
            float d2 = d.x * d.x + d.y * d.y;
#if KINDS > 1
            float r = 0.5 * (own + u_radius[codes_[sorted_[e]].w]);
#else
            float r = own;
#endif
            if (d2 >= r * r) continue;
            float dist = sqrt(d2);
            vec2 u;
            if (dist < 1e-9) {  // coincident: a direction from the pair's numbers, as the numpy twin makes it
                uint j = sorted_[e];
                uint low = min(uint(i), j), high = max(uint(i), j);
                double turn = double(low) * 0.6180339887LF + double(high) * 0.7548776662LF;
                float angle = 6.283185307179586 * float(turn - floor(turn));
                u = (uint(i) == low ? 1.0 : -1.0) * vec2(cos(angle), sin(angle));
            } else {
                u = d * (1.0 / max(dist, 1e-12));
            }
            push += u * (0.5 * (r - dist));
            any = true;
        }
    }
    if (any) {
        float norm = sqrt(push.x * push.x + push.y * push.y) * u_gain;
        scratch_[i].xy = push * (u_gain * min(1.0, 0.5 * own / max(norm, 1e-12)));
    }
}
