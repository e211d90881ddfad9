#version 330 core
#ifdef MORPH_BUFFERS
#extension GL_ARB_shader_storage_buffer_object : require
#endif
// Skinned instancing: one instanced draw per (mesh piece, LOD) covers every agent that wears the
// piece at that LOD. Each instance reads its agent's palette row, written once per frame by the
// animation processor and reused by every pass (colour and shadow).
//
// Why everything but the position is packed into one uvec4 (and the instance into a vec4 and a uvec3):
// on the H100 the draw is bound by how many vertex attributes the shader reads, not by the bone
// fetches or the skinning maths. Reading joints and weights as two more attributes made even an
// unskinned draw as slow as the skinned one; with two attributes per vertex, skinning costs about 2 %
// (docs/BENCHMARKS.md, "Vertex layout"). The bit layouts are written by crowd/draw/render.py: pack_vertices
// and CrowdRenderer.prepare.
//
// Defines: DEPTH_ONLY (shadow pass: position only), UNSKINNED (the benchmark's ceiling: the same
// draw and buffers without bone fetches), TEXTURED (a piece with a base-colour texture: its position
// comes as the float bits of a uvec4 whose w holds the texture coordinate, so it still reads two
// attributes; a third attribute for the coordinate made the H200's draw of a textured crowd 43 %
// slower, docs/BENCHMARKS.md "Textures"), WIDE_UV (with TEXTURED: float coordinates as a third
// attribute, for the rare piece whose coordinates span more than unorm16 can hold to a texel), and
// IMPOSTOR_BAKE (crowd/draw/impostors.py: instance t, a clip's frame at the origin, drawn into its cell of
// the atlas from the view u_bake_*; the cell's box is u_bake_boxes' texel t), and
// MORPH (a piece with morph targets the scene moves: the agent's (target, weight) pairs, which the
// processor wrote into the texel before its joint 0, add each target's deltas to the bind-space
// position and normal before skinning; crowd/draw/morph.py has the textures' layout), and
// UNLIT_PIECES (a cast with KHR_materials_unlit pieces: each vertex says whether its piece is lit).

#if defined(TEXTURED) && defined(WIDE_UV)
in vec3 in_position;   // bind space
in vec2 in_uv;
#ifndef DEPTH_ONLY
out vec2 v_uv;
#endif
#elif defined(TEXTURED)
in uvec4 in_position;  // xyz: the bind-space position's float bits | w: the texture coordinate as
                       // unorm16 x2 across the piece's coordinate box (u_uv_box)
uniform vec4 u_uv_box; // xy: the box's corner, zw: its size
#ifndef DEPTH_ONLY
out vec2 v_uv;
#endif
#else
in vec3 in_position;   // bind space
#endif
in uvec4 in_packed;    // x: normal, snorm10 x3 | y: joints, 4 x u8 (by descending weight)
                       // z: weights 1-3 as unorm10 of 2w (weight 0 = 1 - the rest) | w: colour, RGBA8

#ifdef DEPTH_ONLY
uniform mat4 u_view_proj;  // the shadow cascade's, camera-relative
#else
#include "frame.glsl"
#define u_view_proj u_camera_view_proj
#endif
#include "palette.glsl"
#include "vertex_packing.glsl"
#include "agent_instance.glsl"

#ifdef MORPH
// The vertex table (per vertex: the first entry of its block of deltas, -1: no target moves it) and the
// deltas (per moved vertex and target of its character: snorm16 deltas, two to a uint), in storage
// buffers where the context has them (MORPH_BUFFERS: loads beside the skinning's texture fetches,
// docs/BENCHMARKS.md "Morph targets"), else in textures 4096 entries wide.
#ifdef MORPH_BUFFERS
readonly buffer MorphVertices { int morph_table[]; };
readonly buffer MorphDeltas { uvec4 morph_entries[]; };

int morph_block(int vertex) {
    return morph_table[vertex];
}

uvec3 morph_entry(int index) {
    return morph_entries[index].xyz;
}
#else
uniform isampler2D u_morph_vertices;
uniform usampler2D u_morph_deltas;

ivec2 morph_texel(int index) {
    return ivec2(index & 4095, index >> 12);
}

int morph_block(int vertex) {
    return texelFetch(u_morph_vertices, morph_texel(vertex), 0).x;
}

uvec3 morph_entry(int index) {
    return texelFetch(u_morph_deltas, morph_texel(index), 0).xyz;
}
#endif
uniform int u_morph_vertex_base;      // the table index of this draw's gl_VertexID 0
uniform float u_morph_step;           // metres a position delta's unit stands for

vec2 snorm16x2(uint v) {
    return vec2(ivec2(uvec2(v) << uvec2(16u, 0u)) >> 16);
}

void add_target(int block, vec2 pair, inout vec3 position, inout vec3 normal) {
    uvec3 d = morph_entry(block + int(pair.x));
    vec2 a = snorm16x2(d.x);
    vec2 b = snorm16x2(d.y);
    vec2 c = snorm16x2(d.z);
    position += (pair.y * u_morph_step) * vec3(a, b.x);
    normal += (pair.y * (2.0 / 32767.0)) * vec3(b.y, c);
}

// A vertex no target moves costs one load (its table entry); for the others the agent's pairs follow,
// sorted by size with (0, 0) after the last, so the list ends at the first weight of 0 (an agent moving
// no target costs one fetch more, the same texel for all its vertices). The table first: with storage
// buffers its load is nearly free beside the skinning's texture fetches, the pairs' fetch is not
// (docs/BENCHMARKS.md, "Morph targets").
void morph(ivec3 joint0, inout vec3 position, inout vec3 normal) {
    int block = morph_block(u_morph_vertex_base + gl_VertexID);
    if (block < 0) return;
    ivec3 slot = joint0 - ivec3(1, 0, 0);
    vec4 pairs = texelFetch(u_palette0, slot, 0);
    if (pairs.y == 0.0) return;
    add_target(block, pairs.xy, position, normal);
    if (pairs.w == 0.0) return;
    add_target(block, pairs.zw, position, normal);
    pairs = texelFetch(u_palette1, slot, 0);
    if (pairs.y == 0.0) return;
    add_target(block, pairs.xy, position, normal);
    if (pairs.w == 0.0) return;
    add_target(block, pairs.zw, position, normal);
    pairs = texelFetch(u_palette2, slot, 0);
    if (pairs.y == 0.0) return;
    add_target(block, pairs.xy, position, normal);
    if (pairs.w == 0.0) return;
    add_target(block, pairs.zw, position, normal);
}
#endif

#ifndef DEPTH_ONLY
out vec3 v_world;      // camera-relative
out vec3 v_normal;
out vec4 v_color;
#ifdef LOD_FADE
flat out uint v_fade;  // lod_fade.glsl's code, from the list entry
#endif
#ifdef UNLIT_PIECES
flat out uint v_unlit;  // bit 30 of the packed normal (crowd.draw.packing.UNLIT_BIT)
#endif
#endif
#ifdef IMPOSTOR_BAKE
uniform sampler2D u_bake_boxes;  // (frames, 1): the frame's clip's box: half width, bottom, height, depth half-range
uniform vec3 u_bake_right;       // the view's axes, model space
uniform vec3 u_bake_up;
uniform vec3 u_bake_toward;      // toward the (orthographic) camera
uniform int u_bake_column;       // the view's column of cells
uniform int u_bake_columns;
uniform int u_bake_first;        // the first frame of the atlas layer drawn
uniform int u_bake_rows;         // frames (rows of cells) a layer holds
out float v_bake_depth;          // toward the camera, in units of the box's depth half-range

// Frame t (this instance) into its cell of the layer drawn; frames of other layers off screen.
vec4 bake_position(vec3 p) {
    int row = gl_InstanceID - u_bake_first;
    vec4 box = texelFetch(u_bake_boxes, ivec2(gl_InstanceID, 0), 0);
    vec3 q = vec3(dot(p, u_bake_right), dot(p, u_bake_up), dot(p, u_bake_toward));
    vec2 cell = vec2(0.5 + 0.5 * q.x / box.x, (q.y - box.y) / box.z);
    v_bake_depth = q.z / box.w;
    if (row < 0 || row >= u_bake_rows) return vec4(2.0, 2.0, 2.0, 1.0);
    vec2 atlas = (vec2(float(u_bake_column), float(row)) + cell) / vec2(float(u_bake_columns), float(u_bake_rows));
    return vec4(atlas * 2.0 - 1.0, -v_bake_depth, 1.0);
}
#endif


void main() {
    Agent agent = instance_agent();
#if defined(TEXTURED) && !defined(WIDE_UV)
    vec3 position = uintBitsToFloat(in_position.xyz);
#else
    vec3 position = in_position;
#endif
    vec3 bind_normal = unpack_normal(in_packed.x);
#ifdef UNSKINNED
    vec3 skinned = position;
    vec3 normal = bind_normal;
#else
    ivec3 base = palette_texel(agent.texel);  // an agent's joints sit side by side in one row of one layer
#ifdef MORPH
    morph(base, position, bind_normal);
#endif
    vec4 p = vec4(position, 1.0);
    ivec4 joints = ivec4((uvec4(in_packed.y) >> uvec4(0u, 8u, 16u, 24u)) & 0xFFu);
    vec3 w123 = vec3((uvec3(in_packed.z) >> uvec3(0u, 10u, 20u)) & 0x3FFu) / 2046.0;
    float w0 = 1.0 - (w123.x + w123.y + w123.z);
    // Weights are sorted: nearly every vertex of a game character has one or two influences, so the
    // first two bones are fetched unconditionally and the third and fourth only where their weight is
    // not zero.
    ivec3 t0 = base + ivec3(joints.x, 0, 0);
    ivec3 t1 = base + ivec3(joints.y, 0, 0);
    vec4 r0 = w0 * texelFetch(u_palette0, t0, 0) + w123.x * texelFetch(u_palette0, t1, 0);
    vec4 r1 = w0 * texelFetch(u_palette1, t0, 0) + w123.x * texelFetch(u_palette1, t1, 0);
    vec4 r2 = w0 * texelFetch(u_palette2, t0, 0) + w123.x * texelFetch(u_palette2, t1, 0);
    if (w123.y > 0.0) {
        ivec3 t2 = base + ivec3(joints.z, 0, 0);
        ivec3 t3 = base + ivec3(joints.w, 0, 0);
        r0 += w123.y * texelFetch(u_palette0, t2, 0) + w123.z * texelFetch(u_palette0, t3, 0);
        r1 += w123.y * texelFetch(u_palette1, t2, 0) + w123.z * texelFetch(u_palette1, t3, 0);
        r2 += w123.y * texelFetch(u_palette2, t2, 0) + w123.z * texelFetch(u_palette2, t3, 0);
    }
    vec3 skinned = vec3(dot(r0, p), dot(r1, p), dot(r2, p));
    vec3 normal = vec3(dot(r0.xyz, bind_normal), dot(r1.xyz, bind_normal), dot(r2.xyz, bind_normal));
#endif
    vec2 heading = heading_cos_sin(agent.heading);
    vec3 world = agent.position_scale.xyz + agent.position_scale.w * turn_about_y(heading, skinned);
#ifdef IMPOSTOR_BAKE
    gl_Position = bake_position(world);
#else
    gl_Position = u_view_proj * vec4(world, 1.0);
#endif
#ifndef DEPTH_ONLY
    v_world = world;
    v_normal = turn_about_y(heading, normal);
    v_color = unpack_rgba8(in_packed.w) * agent.tint;
#ifdef LOD_FADE
    v_fade = agent.fade;
#endif
#ifdef UNLIT_PIECES
    v_unlit = (in_packed.x >> 30u) & 1u;
#endif
#endif
#if defined(TEXTURED) && defined(WIDE_UV) && !defined(DEPTH_ONLY)
    v_uv = in_uv;
#elif defined(TEXTURED) && !defined(DEPTH_ONLY)
    v_uv = u_uv_box.xy + u_uv_box.zw * (vec2((uvec2(in_position.w) >> uvec2(0u, 16u)) & 0xFFFFu) / 65535.0);
#endif
}
