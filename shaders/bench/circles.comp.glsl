#version 430
// FLAME GPU 2's "circles" agent step, in 2D, on this project's grid (crowd/sim/gpu/grid.py): each
// agent reads every agent in the 3 x 3 cells (cells one radius wide) around its own, in the grid's
// order, and moves by the mean of sin(-2 pi d / r) x the repulsion along each pair closer than r.
// Positions are read from the grid's sorted copy and written to the other buffer, so no agent sees a
// half-moved step.
layout(local_size_x = 256) in;
layout(std430, binding = 0) buffer Points { vec4 points_[]; };
layout(std430, binding = 10) buffer Cell { uint cell_[]; };
layout(std430, binding = 12) buffer First { uint first_[]; };
layout(std430, binding = 14) buffer Sorted { uint sorted_[]; };
layout(std430, binding = 15) buffer Moved { vec4 moved_[]; };
layout(std430, binding = 16) buffer Payload { vec4 payload_[]; };  // each slot's agent's point
uniform int u_n;
uniform int u_side;
uniform float u_radius;
uniform float u_repulse;
uniform float u_extent;

void main() {
    // A thread a slot of the grid, in cell order: neighbouring threads read the same cells.
    uint slot = gl_GlobalInvocationID.x;
    if (slot >= uint(u_n)) return;
    int i = int(sorted_[slot]);
    vec2 p = payload_[slot].xy;
    int c = int(cell_[i]);
    vec2 force = vec2(0.0);
    uint count = 0u, read = 0u;
    for (int row = -1; row <= 1; row++) {
        int middle = c + row * u_side;
        uint lo = first_[middle - 1], hi = first_[middle + 2];
        for (uint e = lo; e < hi; e++) {
            read++;
            if (e == slot) continue;
            vec2 d = payload_[e].xy - p;
            float separation = sqrt(d.x * d.x + d.y * d.y);
            if (separation < u_radius && separation > 0.0) {
                float k = sin((separation / u_radius) * 3.141 * -2.0) * u_repulse;
                force += k * (d / separation);
                count++;
            }
        }
    }
    force /= float(max(count, 1u));
    moved_[i] = vec4(clamp(p + force, vec2(0.0), vec2(u_extent)), float(read), length(force));
}
