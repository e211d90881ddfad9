#version 430
// Every agent's 32-byte record (crowd/draw/cull_lists.py has the layout), packed on the GPU from the GPU
// AI's state (crowd/sim/gpu/state.py), the twin of crowd.draw.records.RecordPacker: the position
// relative to the eye and the scale, the palette texel of joint 0 in the ring slot its body is drawn
// from, the tint with the character above it, the heading as snorm16 cos and sin, the variation choices.
layout(local_size_x = 256) in;
layout(std430, binding = 0) buffer Motion { vec4 motion_[]; };   // x, z, vx, vz (relative to the origin)
layout(std430, binding = 1) buffer Heading { vec4 heading_[]; }; // hx, hz, phase, scale
layout(std430, binding = 5) buffer Codes { ivec4 codes_[]; };    // state, action, health, kind
layout(std430, binding = 6) buffer Looks { uvec4 looks_[]; };    // tint, head, weapon + 1, spawned_step
layout(std430, binding = 17) buffer TexelBase { uint texel_base_[]; };  // each agent's joint 0 in a ring slot starting at row 0
layout(std430, binding = 18) buffer Records { uvec4 records_[]; };       // two an agent

uniform int u_n;
uniform vec3 u_eye;            // relative to the crowd's origin
uniform uint u_row_code;       // texel code of the first row of the slot most bodies are drawn from
uniform uint u_latest_code;    // and of this frame's slot, for agents that were not there then
uniform int u_born_limit;      // agents with a spawned_step above it came after the read-back's frame (-1: none)
uniform int u_head_shift;      // where the head group's choice goes in fields.w (-1: no head group)
uniform int u_held_shift;      // and the held-weapon group's (-1: none)
uniform int u_weapon_first[KINDS];  // each character's first weapon among the cast's
const uint CHARACTER_SHIFT = 24u;

uint snorm16(float v) {
    return uint(int(roundEven(v * 32767.0))) & 0xFFFFu;
}

void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= u_n) return;
    vec4 m = motion_[i];
    vec4 h = heading_[i];
    ivec4 c = codes_[i];
    uvec4 look = looks_[i];
    vec3 position = vec3(m.x, 0.0, m.y) - u_eye;
    uint row = u_born_limit >= 0 && int(look.w) > u_born_limit ? u_latest_code : u_row_code;
    uint tint = (look.x & 0xFFFFFFu) | (uint(c.w) << CHARACTER_SHIFT);
    uint heading = snorm16(h.y) | (snorm16(h.x) << 16);  // (cos yaw, sin yaw) = (hz, hx) for a unit heading
    uint choices = 0u;
    if (u_head_shift >= 0) choices |= look.y << uint(u_head_shift);
    if (u_held_shift >= 0 && look.z > 0u && c.x < 4) choices |= (look.z - uint(u_weapon_first[c.w])) << uint(u_held_shift);
    records_[2 * i] = floatBitsToUint(vec4(position, h.w));
    records_[2 * i + 1] = uvec4(texel_base_[i] + row, tint, heading, choices);
}
