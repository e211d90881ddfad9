#version 330 core
// bench/vertex_layout_probe.py: the skinned draw under different vertex layouts and skinning variants,
// to find what bounds it (docs/BENCHMARKS.md, "Vertex layout"). Not used by the demo; the demo's
// shader is skin.vert.glsl, which has the PACKED layout and the default (two bones + branch) skinning.
//
// Layout defines: SEPARATE (the first renderer: 5 vertex + 4 instance attributes) or PACKED
// (skin.vert.glsl's: position + uvec4 per vertex, vec4 + uvec3 per instance).
// Skinning defines: UNSKINNED, UNSKINNED_READS_JOINTS (unskinned, but the joint and weight attributes
// are read), ONE_BONE (first bone at full weight: the weights are never read), FOUR_BONES (four
// unconditional bones, 12 fetches); none of them: two bones + a branch for bones 3 and 4.

in vec3 in_position;
#ifdef PACKED
in uvec4 in_packed;
in vec4 i_position_scale;
in uvec3 i_packed;
#else
in vec4 in_normal;
in uvec4 in_joints;
in vec4 in_weights;
in vec4 in_color;
in vec3 i_position;
in vec2 i_yaw_scale;
in uvec2 i_palette;
in vec4 i_tint;
#endif

uniform mat4 u_view_proj;
uniform sampler2DArray u_palette0;  // the probe's crowd fits one layer (vertex_layout_probe.py checks)
uniform sampler2DArray u_palette1;
uniform sampler2DArray u_palette2;

out vec3 v_world;
out vec3 v_normal;
out vec4 v_color;

vec4 unpack_rgba8(uint v) {
    return vec4((uvec4(v) >> uvec4(0u, 8u, 16u, 24u)) & 0xFFu) / 255.0;
}

void main() {
#ifdef PACKED
    vec3 bind_normal = vec3(ivec3(uvec3(in_packed.x) << uvec3(22u, 12u, 2u)) >> 22) / 511.0;
    ivec4 joints = ivec4((uvec4(in_packed.y) >> uvec4(0u, 8u, 16u, 24u)) & 0xFFu);
    vec3 w123 = vec3((uvec3(in_packed.z) >> uvec3(0u, 10u, 20u)) & 0x3FFu) / 2046.0;
    vec4 weights = vec4(1.0 - (w123.x + w123.y + w123.z), w123);
    vec4 color = unpack_rgba8(in_packed.w) * unpack_rgba8(i_packed.y);
    ivec3 base = ivec3(i_packed.x & 0xFFFu, i_packed.x >> 12, 0);
    vec2 cs = vec2(ivec2(uvec2(i_packed.z) << uvec2(16u, 0u)) >> 16) / 32767.0;
    float c = cs.x, s = cs.y, scale = i_position_scale.w;
    vec3 origin = i_position_scale.xyz;
#else
    vec3 bind_normal = in_normal.xyz;
    ivec4 joints = ivec4(in_joints);
    vec4 weights = in_weights;
    vec4 color = in_color * i_tint;
    ivec3 base = ivec3(i_palette, 0);
    float c = cos(i_yaw_scale.x), s = sin(i_yaw_scale.x), scale = i_yaw_scale.y;
    vec3 origin = i_position;
#endif
    vec4 p = vec4(in_position, 1.0);
#if defined(UNSKINNED) || defined(UNSKINNED_READS_JOINTS)
    vec3 skinned = in_position;
    vec3 normal = bind_normal;
#ifdef UNSKINNED_READS_JOINTS
    color.r += 1e-30 * float(joints.x) * weights.x;  // too small to change a pixel, but the compiler must read both
#endif
#else
    ivec3 t0 = base + ivec3(joints.x, 0, 0);
    ivec3 t1 = base + ivec3(joints.y, 0, 0);
    ivec3 t2 = base + ivec3(joints.z, 0, 0);
    ivec3 t3 = base + ivec3(joints.w, 0, 0);
#if defined(ONE_BONE)
    vec4 r0 = texelFetch(u_palette0, t0, 0), r1 = texelFetch(u_palette1, t0, 0), r2 = texelFetch(u_palette2, t0, 0);
#else
    vec4 r0 = weights.x * texelFetch(u_palette0, t0, 0) + weights.y * texelFetch(u_palette0, t1, 0);
    vec4 r1 = weights.x * texelFetch(u_palette1, t0, 0) + weights.y * texelFetch(u_palette1, t1, 0);
    vec4 r2 = weights.x * texelFetch(u_palette2, t0, 0) + weights.y * texelFetch(u_palette2, t1, 0);
#ifndef FOUR_BONES
    if (weights.z > 0.0)
#endif
    {
        r0 += weights.z * texelFetch(u_palette0, t2, 0) + weights.w * texelFetch(u_palette0, t3, 0);
        r1 += weights.z * texelFetch(u_palette1, t2, 0) + weights.w * texelFetch(u_palette1, t3, 0);
        r2 += weights.z * texelFetch(u_palette2, t2, 0) + weights.w * texelFetch(u_palette2, t3, 0);
    }
#endif
    vec3 skinned = vec3(dot(r0, p), dot(r1, p), dot(r2, p));
    vec3 normal = vec3(dot(r0.xyz, bind_normal), dot(r1.xyz, bind_normal), dot(r2.xyz, bind_normal));
#endif
    vec3 local = vec3(c * skinned.x + s * skinned.z, skinned.y, -s * skinned.x + c * skinned.z);
    vec3 world = origin + scale * local;
    gl_Position = u_view_proj * vec4(world, 1.0);
    v_world = world;
    v_normal = vec3(c * normal.x + s * normal.z, normal.y, -s * normal.x + c * normal.z);
    v_color = color;
}
