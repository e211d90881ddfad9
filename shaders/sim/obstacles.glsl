// The GPU twin of crowd.sim.obstacles (and crowd.asset.town.Obstacles): the town's signed distance field,
// bilinear, repeating every period; keep-out along its gradient; the chasers' flow field round the
// buildings. Compiled in only with a town (TOWN).
layout(std430, binding = 11) buffer Field { float field_[]; };  // (n + 1) x (n + 1) corners, row i = x
layout(std430, binding = 12) buffer Flow { uint flow_[]; };     // FLOW_CELLS^2 (x-major): di + 2, dj + 2 << 4, usable << 8
uniform vec2 u_origin_mod;    // the crowd's origin modulo the period: field coordinates of relative positions
uniform float u_period, u_cell;
uniform int u_field_n;        // corners a side, less one
uniform vec3 u_flow_corner;   // the flow window's first cell's corner (relative), and 1 once a field is in
const float CLEARANCE = 0.35, FLOW_CELL = 1.0, FLOW_DIRECT = 3.0;
const int FLOW_CELLS = 96;

float field_at(int i, int j) {
    return field_[i * (u_field_n + 1) + j];
}

float obstacle_distance(vec2 p) {
    vec2 uv = mod(p + u_origin_mod, u_period) / u_cell;
    int i = min(int(floor(uv.x)), u_field_n - 1), j = min(int(floor(uv.y)), u_field_n - 1);
    vec2 f = uv - vec2(i, j);
    return (field_at(i, j) * (1.0 - f.x) + field_at(i + 1, j) * f.x) * (1.0 - f.y) + (field_at(i, j + 1) * (1.0 - f.x) + field_at(i + 1, j + 1) * f.x) * f.y;
}

vec2 obstacle_gradient(vec2 p) {
    float h = 0.5 * u_cell;
    vec2 g = vec2(obstacle_distance(p + vec2(h, 0.0)) - obstacle_distance(p - vec2(h, 0.0)),
                  obstacle_distance(p + vec2(0.0, h)) - obstacle_distance(p - vec2(0.0, h)));
    return g / max(length(g), 1e-12);
}

vec2 keep_out(vec2 p, float half_width) {  // out along the gradient until CLEARANCE, aiming 5 mm past it; inside the world
    for (int k = 0; k < 4; k++) {
        float d = obstacle_distance(p);
        if (d >= CLEARANCE) break;
        p = clamp(p + obstacle_gradient(p) * (CLEARANCE + 0.005 - d), -half_width, half_width);
    }
    return p;
}

vec2 flow_direction(vec2 p, vec2 to_player, float straight) {  // a chaser's way toward the player
    vec2 u = to_player / max(straight, 1e-12);
    if (u_flow_corner.z < 0.5) return u;
    ivec2 c = ivec2(floor((p - u_flow_corner.xy) / FLOW_CELL));
    if (c.x < 1 || c.x >= FLOW_CELLS - 1 || c.y < 1 || c.y >= FLOW_CELLS - 1 || straight <= FLOW_DIRECT) return u;
    uint step = flow_[c.x * FLOW_CELLS + c.y];
    if ((step & 0x100u) == 0u) return u;
    ivec2 to = ivec2(int(step & 0xFu) - 2, int((step >> 4) & 0xFu) - 2);
    vec2 t = u_flow_corner.xy + (vec2(c + to) + 0.5) * FLOW_CELL - p;  // toward that neighbour's centre
    return t / max(length(t), 1e-12);
}
