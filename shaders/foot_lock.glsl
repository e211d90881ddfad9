// Foot lock (crowd.anim.foot_lock says what and why; FootLockTwin there is this file's float64 twin,
// the same steps in the same order: change one, change the other). Included by processor.comp.glsl
// after its shared arrays, under FOOT_LOCK: the invocation of the first leg's ankle reads the agent's
// blended locals from shared memory and, leg after leg (a leg's step waits for the others), advances
// each leg's state and, where its correction is not ~0, rewrites its hip's, knee's and ankle's locals
// there before the hierarchy is composed.
//
// Defines: LEG_COUNT (1..4), CONTACT_M, STEP_SHIFT_M, STEP_TWIST_RAD, HOLD_SHIFT_M, HOLD_TWIST_RAD, STEP_LIFT_M,
// RESET_M, RESET_RAD, CORRECTION_EPS, MIN_FORWARD_HORIZONTAL.

layout(std430, binding = 0) buffer FootLockState { vec4 lock_state[]; };       // agent * LEG_COUNT + leg
layout(std430, binding = 1) readonly buffer AgentMotion { vec4 agent_motion[]; };  // ground step x, z; front x, z times the scale
uniform ivec4 u_leg_joints[LEG_COUNT];  // hip's parent (-1: none), hip, knee, ankle
uniform int u_leg_toe[LEG_COUNT];       // the toe joint (-1: none)
uniform vec3 u_leg_forward[LEG_COUNT];  // the foot's forward axis in the ankle's rest-pose frame
uniform vec2 u_leg_lowest[LEG_COUNT];   // the ankle's and the toe's lowest heights
uniform float u_lock_decay;             // exp(-dt / RELEASE_S) for this frame
uniform float u_step_advance;           // dt / STEP_S: a step's progress this frame
const float FREE = 0.0, HELD = 1.0, HELD_TOE = 2.0, STEPPING = 3.0;  // a leg state's w (FootLockTwin says what each means)

Affine shared_local(int index) {
    return Affine(s_local0[index], s_local1[index], s_local2[index]);
}

mat3 linear_part(Affine m) {  // columns of the 3x3 part
    return mat3(m.r0.x, m.r1.x, m.r2.x, m.r0.y, m.r1.y, m.r2.y, m.r0.z, m.r1.z, m.r2.z);
}

mat3 rotation_part(Affine m) {  // without the uniform scale
    mat3 l = linear_part(m);
    return l * (1.0 / length(l[0]));
}

Affine times_linear(mat3 q, Affine m) {  // q applied after m's linear part; m's translation kept
    mat3 l = q * linear_part(m);
    return Affine(vec4(l[0].x, l[1].x, l[2].x, m.r0.w), vec4(l[0].y, l[1].y, l[2].y, m.r1.w), vec4(l[0].z, l[1].z, l[2].z, m.r2.w));
}

mat3 axis_rotation(vec3 axis, vec2 cs) {  // about a unit axis, by the angle whose cosine and sine are cs
    float c = cs.x, s = cs.y, t = 1.0 - c;
    vec3 a = axis;
    return mat3(t * a.x * a.x + c, t * a.x * a.y + s * a.z, t * a.x * a.z - s * a.y,
                t * a.x * a.y - s * a.z, t * a.y * a.y + c, t * a.y * a.z + s * a.x,
                t * a.x * a.z + s * a.y, t * a.y * a.z - s * a.x, t * a.z * a.z + c);
}

mat3 yaw_rotation(float angle) {  // front (0, 0, 1) to (sin, 0, cos), as an agent's yaw
    float c = cos(angle), s = sin(angle);
    return mat3(c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c);
}

// An angle in [0, pi] as (cosine, sine) from its cosine, and the difference of two such: the leg's
// turns are taken without acos (crowd.anim.foot_lock.solve_leg says why).
vec2 cos_sin(float c) {
    c = clamp(c, -1.0, 1.0);
    return vec2(c, sqrt(max(1.0 - c * c, 0.0)));
}

vec2 difference(vec2 a, vec2 b) {
    return vec2(a.x * b.x + a.y * b.y, a.y * b.x - a.x * b.y);
}

float wrap_angle(float a) {
    return a - 6.283185307179586 * floor((a + 3.141592653589793) / 6.283185307179586);
}

vec3 origin_of(Affine m) {
    return vec3(m.r0.w, m.r1.w, m.r2.w);
}

// The model-space matrix of `joint` of the agent whose locals start at shared index `base`.
Affine shared_global(int base, int joint) {
    Affine g = shared_local(base + joint);
    int p = parent_of(joint);
    for (int k = 0; k < MAX_JOINTS && p >= 0; ++k) {
        g = compose(shared_local(base + p), g);
        p = parent_of(p);
    }
    return g;
}

vec2 turn_xz(vec2 v, float angle) {  // a world (x, z) vector turned about +Y, as an agent's yaw turns its front
    float c = cos(angle), s = sin(angle);
    return vec2(c * v.x + s * v.y, -s * v.x + c * v.y);
}

void lock_leg(int agent, int base, int leg) {
    ivec4 chain = u_leg_joints[leg];
    Affine parent = chain.x >= 0 ? shared_global(base, chain.x) : Affine(vec4(1, 0, 0, 0), vec4(0, 1, 0, 0), vec4(0, 0, 1, 0));
    Affine hip = compose(parent, shared_local(base + chain.y));
    Affine knee = compose(hip, shared_local(base + chain.z));
    Affine ankle = compose(knee, shared_local(base + chain.w));
    vec3 p = origin_of(ankle);
    int toe = u_leg_toe[leg];
    vec3 t = toe >= 0 ? origin_of(compose(ankle, shared_local(base + toe))) : p;
    vec3 forward = linear_part(ankle) * u_leg_forward[leg];
    bool has_yaw = length(forward.xz) > MIN_FORWARD_HORIZONTAL * length(forward);
    vec4 motion = agent_motion[agent];
    float scale = length(motion.zw);
    float sy = motion.z / scale, cy = motion.w / scale;  // the front: (sin yaw, cos yaw)
    float foot_yaw = atan(sy, cy) + atan(forward.x, forward.z);
    vec2 ankle_w = scale * vec2(cy * p.x + sy * p.z, -sy * p.x + cy * p.z);  // from the ground point, world orientation
    vec3 toe_m = t - p;
    vec2 toe_w = scale * vec2(cy * toe_m.x + sy * toe_m.z, -sy * toe_m.x + cy * toe_m.z);  // the toe from the ankle
    bool ankle_down = p.y <= u_leg_lowest[leg].x + CONTACT_M / scale;
    bool toe_down = t.y <= u_leg_lowest[leg].y + CONTACT_M / scale;
    int index = agent * LEG_COUNT + leg;
    vec4 s = lock_state[index];
    bool stepping = s.w >= STEPPING;
    bool kept = s.w == HELD || s.w == HELD_TOE || stepping;  // a point held (a stepping foot's: where it left)
    // The correction (crowd.anim.foot_lock.FootLockTwin): the foot turned about its ankle by c.z, then
    // shifted by c.xy, so that its held point (the ankle's, or the toe's) is where it is held.
    float cyaw = kept ? wrap_angle(s.z - foot_yaw) : s.z * u_lock_decay;
    vec2 hold_xy = s.xy - motion.xy;
    vec3 c = vec3(kept ? hold_xy - (s.w == HELD_TOE ? turn_xz(toe_w, cyaw) : vec2(0.0)) - ankle_w : s.xy * u_lock_decay, cyaw);
    bool reset = length(c.xy) > RESET_M * scale || abs(c.z) > RESET_RAD;  // a respawn or a teleport
    if (reset) c = vec3(0.0);
    // A step: the foot rises and comes down, and moves from where it left to where its clip puts it in
    // the middle half, clear of the ground.
    float progress = stepping ? s.w - STEPPING + u_step_advance : 0.0;
    bool landed = stepping && (progress >= 1.0 || reset);
    float lift = 0.0;
    if (stepping) {
        float e = min(progress, 1.0);
        float m = clamp((e - 0.25) * 2.0, 0.0, 1.0);
        c *= 1.0 - m * m * m * (m * (6.0 * m - 15.0) + 10.0);
        lift = landed ? 0.0 : STEP_LIFT_M * sin(3.141592653589793 * e) / scale;
    }
    bool hold = (ankle_down || toe_down) && has_yaw;
    // Held too far: a step where every other leg is held (the earlier legs' states are this run's, the
    // later ones' the last run's, as in the twin), and beyond the hold limits anyway (a hop).
    float shift = length(c.xy);
    bool over = hold && !stepping && (shift > STEP_SHIFT_M * scale || abs(c.z) > STEP_TWIST_RAD);
    bool planted = true;
    for (int other = 0; other < LEG_COUNT; ++other) {
        float w = lock_state[agent * LEG_COUNT + other].w;
        if (other != leg && w != HELD && w != HELD_TOE) planted = false;
    }
    bool start = over && (planted || shift > HOLD_SHIFT_M * scale || abs(c.z) > HOLD_TWIST_RAD);
    hold = hold && (!stepping || landed);
    bool by_toe = hold && !ankle_down;  // held by the ankle while it is down, else by the toe (the heel is up)
    vec2 point = ankle_w + c.xy + (by_toe ? turn_xz(toe_w, c.z) : vec2(0.0));
    lock_state[index] = start ? vec4(ankle_w + c.xy, wrap_angle(foot_yaw + c.z), STEPPING)
                      : stepping && !landed ? vec4(hold_xy, s.z, STEPPING + progress)
                      : hold ? vec4(point, wrap_angle(foot_yaw + c.z), by_toe ? HELD_TOE : HELD) : vec4(c, FREE);
    if (!(length(c.xy) > CORRECTION_EPS * scale || abs(c.z) > CORRECTION_EPS || lift > 0.0)) return;  // as the clips put it
    vec2 d = vec2(cy * c.x - sy * c.y, sy * c.x + cy * c.y) / scale;
    vec3 target = p + vec3(d.x, lift, d.y);

    // Two-bone IK (crowd.anim.foot_lock.solve_leg).
    vec3 h = origin_of(hip), k = origin_of(knee);
    float thigh = length(k - h), shin = length(p - k);
    float low = abs(thigh - shin) + 1e-5 * (thigh + shin), high = (thigh + shin) * (1.0 - 1e-5);
    float now = length(p - h), then = clamp(length(target - h), min(low, now), max(high, now));
    vec2 hip_delta = difference(cos_sin((thigh * thigh + then * then - shin * shin) / (2.0 * thigh * then)),
                                cos_sin((thigh * thigh + now * now - shin * shin) / (2.0 * thigh * now)));
    vec2 knee_delta = difference(cos_sin((thigh * thigh + shin * shin - then * then) / (2.0 * thigh * shin)),
                                 cos_sin((thigh * thigh + shin * shin - now * now) / (2.0 * thigh * shin)));
    vec3 bend = cross(p - h, k - h);
    bend = length(bend) > 1e-9 * thigh * (thigh + shin) ? normalize(bend) : normalize(linear_part(hip)[0]);
    vec3 swing_axis = cross(p - h, target - h);
    float swing_len = length(swing_axis);
    bool swings = swing_len > 1e-12 * thigh * thigh;
    float swing_dot = dot(p - h, target - h);
    vec2 swing = swings ? vec2(swing_dot, swing_len) / length(vec2(swing_dot, swing_len)) : vec2(1.0, 0.0);
    swing_axis = swings ? swing_axis / swing_len : bend;
    mat3 hip_turn = axis_rotation(swing_axis, swing) * axis_rotation(bend, hip_delta);
    mat3 knee_turn = axis_rotation(bend, knee_delta);
    mat3 parent_rot = rotation_part(parent);
    mat3 hip_rot = rotation_part(hip);
    mat3 knee_rot = rotation_part(knee);
    Affine hip_local = times_linear(transpose(parent_rot) * hip_turn * parent_rot, shared_local(base + chain.y));
    Affine knee_local = times_linear(transpose(hip_rot) * knee_turn * hip_rot, shared_local(base + chain.z));
    Affine ankle_local = times_linear(transpose(knee_rot) * transpose(knee_turn) * transpose(hip_turn) * yaw_rotation(c.z) * knee_rot,
                                      shared_local(base + chain.w));
    s_local0[base + chain.y] = hip_local.r0;
    s_local1[base + chain.y] = hip_local.r1;
    s_local2[base + chain.y] = hip_local.r2;
    s_local0[base + chain.z] = knee_local.r0;
    s_local1[base + chain.z] = knee_local.r1;
    s_local2[base + chain.z] = knee_local.r2;
    s_local0[base + chain.w] = ankle_local.r0;
    s_local1[base + chain.w] = ankle_local.r1;
    s_local2[base + chain.w] = ankle_local.r2;
}
