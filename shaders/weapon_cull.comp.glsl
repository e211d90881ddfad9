#version 430
// Weapons on the GPU-driven path (crowd/draw/weapons.py): the CPU places every armed agent's weapon
// in its agent's model space from the read-back (3x4 rows, sorted by weapon mesh); this pass keeps
// those whose agent the body cull (cull.comp.glsl) found visible, each with its agent's record (whose
// transform weapon.vert.glsl applies as skin.vert.glsl does for the body), compacted into the list of
// its (weapon, LOD) mesh, and counts them in that mesh's indirect command. A weapon is drawn exactly when its agent is, at the
// agent's LOD (its shadow at the agent's shadow LOD), the prop's coarsest where it has fewer.
layout(local_size_x = 256) in;

struct Rows { vec4 r0; vec4 r1; vec4 r2; };

layout(std430, binding = 0) readonly buffer Placed { Rows placed[]; };
layout(std430, binding = 1) readonly buffer Owner { uvec2 owner[]; };     // (agent, weapon mesh)
struct Shown { Rows rows; vec4 position_scale; uvec4 fields; };             // weapons.py's INSTANCE_DTYPE
layout(std430, binding = 2) writeonly buffer ShownList { Shown shown[]; }; // (w, lod)'s list starts at lod * u_count + u_start[w]
layout(std430, binding = 3) buffer Commands { uint commands[]; };         // draw w * u_lod_count + lod
layout(std430, binding = 4) readonly buffer Visible { uint visible[]; };  // per agent, from the body cull
struct Record { vec4 position_scale; uvec4 fields; };  // cull_common.glsl's: fields.z is cos, sin as snorm16 x2
layout(std430, binding = 5) readonly buffer Agents { Record agents[]; };

uniform uint u_count;
uniform uint u_shadow;     // 0: the colour pass's weapons (agents drawn); 1 + k: shadow cascade k's (agents in its volume)
uniform uint u_list_base;  // entries before this run's lists (a cascade's: k * lods * u_count)
uniform uint u_command_base;  // commands before this run's
uniform uint u_lod_count;  // LODs per weapon
uniform uint u_start[WEAPONS];  // (a define: the cast's weapon meshes) each weapon's first entry in its LOD's lists

void main() {
    uint k = gl_GlobalInvocationID.x;
    if (k >= u_count) return;
    uvec2 o = owner[k];
    uint v = visible[o.x];
    if ((v & (u_shadow == 0u ? 0xFFFFu : 0x8000u << u_shadow)) == 0u) return;  // bit 16 + k: in cascade k's volume
    uint lod = min(u_shadow == 0u ? (v & 0xFFFFu) - 1u : (v >> 20) & 255u, u_lod_count - 1u);
    uint slot = atomicAdd(commands[(u_command_base + o.y * u_lod_count + lod) * 5u + 1u], 1u);
    Record a = agents[o.x];
    shown[u_list_base + lod * u_count + u_start[o.y] + slot] = Shown(placed[k], a.position_scale, a.fields);
}
