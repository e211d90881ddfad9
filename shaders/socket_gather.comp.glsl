#version 430
// The weapons' socket read-back for a crowd on the GPU (crowd/draw/gpu_sockets.py): every armed agent
// that may be drawn as a mesh (within the impostors' reach, for a character that has them) appends
// its number, weapon, state and spawn step, and the three rows of its socket joint's skinning matrix
// copied bit for bit out of the palette, to this frame's slot of a ring the CPU reads N frames later.
// The survivor's row (u_n) comes from uniforms. With FEET, the foot-skate sample's agents in steady
// locomotion (threads after the survivor's) append their frame (motion, heading) and their foot joints'
// rows in one block. The order of the entries is the atomics'; the CPU sorts them.
layout(local_size_x = 256) in;
layout(std430, binding = 0) buffer Motion { vec4 motion_[]; };
layout(std430, binding = 5) buffer Codes { ivec4 codes_[]; };
layout(std430, binding = 1) buffer Heading { vec4 heading_[]; }; // hx, hz, phase, scale
layout(std430, binding = 6) buffer Looks { uvec4 looks_[]; };    // tint, head, weapon + 1, spawned_step
layout(std430, binding = 17) buffer TexelBase { uint texel_base_[]; };
struct Entry {
    uvec4 who;  // agent, weapon, state, spawned_step
    vec4 row0;
    vec4 row1;
    vec4 row2;
};
layout(std430, binding = 19) buffer Gathered {
    uint count_;
    uint pad0_, pad1_, pad2_;
    Entry entries_[];
};
#include "palette.glsl"

uniform int u_n;
uniform int u_capacity;
uniform uint u_row_code;          // this frame's palette slot
uniform vec3 u_eye;               // relative to the crowd's origin
uniform float u_reach2;           // squared metres within which an impostor character's agents are meshes
uniform int u_socket[WEAPONS];    // each weapon's socket joint
uniform int u_far[KINDS];         // 1 where a character has impostors (its far agents hold their weapon in the impostor)
uniform int u_extra_weapon;       // the survivor's weapon (-1: none)
uniform uint u_extra_code;        // its joint 0's texel code, this frame's slot
#ifdef FEET
uniform int u_sample[SAMPLE];     // the foot-skate sample's agents
uniform int u_samples;
uniform int u_feet[FEET];         // the foot joints
const uint FRAME_ENTRY = 0xFFFFFFFFu, FOOT_ENTRY = 0xFFFF0000u;
#endif

void append(uint slot, uvec4 who, uint code) {
    if (slot >= uint(u_capacity)) return;  // (counted still: the CPU grows the ring for the next frames)
    ivec3 t = palette_texel(code);
    entries_[slot] = Entry(who, texelFetch(u_palette0, t, 0), texelFetch(u_palette1, t, 0), texelFetch(u_palette2, t, 0));
}

void main() {
    int i = int(gl_GlobalInvocationID.x);
#ifdef FEET
    if (i > u_n && i <= u_n + u_samples) {
        int a = u_sample[i - u_n - 1];
        ivec4 c = codes_[a];
        if (c.y != 0 || (c.x != 0 && c.x != 1)) return;  // steady locomotion only: no action, wandering or chasing
        if (u_far[c.w] != 0) {  // past the impostors' reach its row holds its key alone (processor.comp.glsl)
            vec2 d = motion_[a].xy - u_eye.xz;
            if (d.x * d.x + u_eye.y * u_eye.y + d.y * d.y > u_reach2) return;
        }
        uint slot = atomicAdd(count_, uint(FEET + 1));
        uint born = looks_[a].w;
        if (slot < uint(u_capacity)) entries_[slot] = Entry(uvec4(uint(a), FRAME_ENTRY, uint(c.x), born), motion_[a], heading_[a], vec4(0.0));
        for (int k = 0; k < FEET; k++) append(slot + 1u + uint(k), uvec4(uint(a), FOOT_ENTRY | uint(k), uint(c.x), born), texel_base_[a] + u_row_code + uint(u_feet[k]));
        return;
    }
#endif
    if (i > u_n) return;
    int weapon, state;
    uint code, born;
    if (i == u_n) {
        if (u_extra_weapon < 0) return;
        weapon = u_extra_weapon;
        state = 0;
        born = 0u;
        code = u_extra_code;
    } else {
        uvec4 look = looks_[i];
        if (look.z == 0u) return;
        ivec4 c = codes_[i];
        if (u_far[c.w] != 0) {
            vec2 d = motion_[i].xy - u_eye.xz;
            if (d.x * d.x + u_eye.y * u_eye.y + d.y * d.y > u_reach2) return;
        }
        weapon = int(look.z) - 1;
        state = c.x;
        born = look.w;
        code = texel_base_[i] + u_row_code;
    }
    append(atomicAdd(count_, 1u), uvec4(uint(i), uint(weapon), uint(state), born), code + uint(u_socket[weapon]));
}
