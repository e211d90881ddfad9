// The crowd's state on the GPU (crowd/sim/gpu_state.py packs and unpacks it): one vec4 or ivec4 per
// agent per buffer, positions relative to the crowd's origin. The numpy AI's names, grouped by what a
// pass reads together.
layout(std430, binding = 0) buffer Motion { vec4 motion_[]; };   // x, z, vx, vz
layout(std430, binding = 1) buffer Heading { vec4 heading_[]; }; // hx, hz, phase, scale
layout(std430, binding = 2) buffer Timers { vec4 timers_[]; };   // state_time, action_time, cooldown, aware
layout(std430, binding = 3) buffer Goal { vec4 goal_[]; };       // tx, tz, pause, reaction
layout(std430, binding = 4) buffer Traits { vec4 traits_[]; };   // speed_factor, walk_top, chase_top, runner
layout(std430, binding = 5) buffer Codes { ivec4 codes_[]; };    // state, action, health, kind
layout(std430, binding = 6) buffer Looks { uvec4 looks_[]; };    // tint (RGBA8), head, weapon + 1, spawned_step
layout(std430, binding = 7) buffer Scratch { vec4 scratch_[]; }; // push x, push z, to player x, to player z
// Per character (crowd.sim.motion.Motion), in the cast's order.
struct Kind {
    vec4 loco;      // walk_stride, run_stride, run_speed, walk_slowest
    vec4 more;      // idle's duration, walk_speed, upper-body mask row (-1: none), has pivots
    vec4 length;    // seconds each action lasts: none, attack, hit, death (NEVER: no end)
    vec4 clip;      // each action's clip: 0, attack, hit, death
    vec4 roles;     // attack, hit and death clips (-1: none), 0
    vec4 loco_clip; // idle, walk and run clips, 0
};
layout(std140, binding = 0) uniform Kinds { Kind kinds[KINDS]; };
// The game's facts, counted by atomics (integer sums: the same whatever order threads add in). The
// first four only grow (the CPU reads them through a ring of copies, and a difference of totals loses
// nothing when a copy is skipped); the state counts are zeroed before each count; a nearest search's
// pair is set to (inf, none) before it.
layout(std430, binding = 8) buffer Counters {
    uint blows;          // attacks that landed on the player
    uint respawns;
    uint kills;          // agents the player's blows killed
    uint hurt;
    uint state_count[8];
    uint nearest_d[2];   // a search's nearest distance (float bits: non-negative floats order as uints): 0 a strike's, 1 a look's
    uint nearest_i[2];   // and the lowest agent at it
    vec2 nearest_at;     // where a look's nearest agent stands (relative to the origin)
    uint near;           // living agents within reach of the count's point (the HUD's)
    int selected;        // the agent whose row follows (the panel's), or -1
    vec4 selected_motion;
    vec4 selected_heading;
    ivec4 selected_codes;
    uint pick_t;         // a click's pick: the nearest hit along its ray (float bits), the lowest agent there,
    uint picked;         // and the request it answers (kept until the next: any later frame's copy carries it)
    uint pick_serial;
    uint pad_;
};

const int WANDER = 0, CHASE = 1, ATTACK = 2, HIT = 3, DYING = 4, DEAD = 5;
const int NO_ACTION = 0, ACT_ATTACK = 1, ACT_HIT = 2, ACT_DEATH = 3;
const float NEVER = 1e30;
