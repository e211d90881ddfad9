#version 410 core
// Weapons on the transform-feedback path (crowd/draw/weapons.py, GL 4.0 to 4.2): the CPU places every
// armed agent's weapon in its agent's model space, with the agent's transform, as on the CPU path; this
// pass keeps, for each of the (up to) 4 (weapon, LOD, pass) lists it fills, those whose agent the body
// cull's visibility (feedback_visible.vert.glsl) shows there, as weapon_cull.comp.glsl does on GL 4.3.
// The geometry shader (weapon_feedback.geom.glsl) appends each to its lists, a stream each.
in vec4 i_row0;
in vec4 i_row1;
in vec4 i_row2;
in vec4 i_position_scale;
in uvec4 i_fields;  // x: the agent | y: the weapon | z: its heading (weapons.py's INSTANCE_DTYPE)

uniform usampler2D u_visible;  // per agent, its visibility word
uniform int u_visible_width;
uniform uint u_lod_count;      // LODs per weapon
// The 4 lists (streams): the pass each is of (0: the colour pass's weapons, agents drawn; 1 + k: shadow
// cascade k's, agents in its volume; -1: none), and its weapon and LOD.
uniform ivec4 u_slot_pass;
uniform uvec4 u_slot_weapon;
uniform uvec4 u_slot_lod;

flat out ivec4 v_emit;
out vec4 v_row0;
out vec4 v_row1;
out vec4 v_row2;
out vec4 v_position_scale;
flat out uvec4 v_fields;

void main() {
    int agent = int(i_fields.x);
    uint v = texelFetch(u_visible, ivec2(agent % u_visible_width, agent / u_visible_width), 0).r;
    for (int s = 0; s < 4; ++s) {
        uint pass = uint(max(u_slot_pass[s], 0));
        bool shown = u_slot_pass[s] >= 0 && (v & (pass == 0u ? 0xFFFFu : 0x8000u << pass)) != 0u;  // bit 16 + k: in cascade k's volume
        uint lod = min(pass == 0u ? (v & 0xFFFFu) - 1u : (v >> 20) & 255u, u_lod_count - 1u);
        v_emit[s] = int(shown && i_fields.y == u_slot_weapon[s] && lod == u_slot_lod[s]);
    }
    v_row0 = i_row0;
    v_row1 = i_row1;
    v_row2 = i_row2;
    v_position_scale = i_position_scale;
    v_fields = i_fields;
}
