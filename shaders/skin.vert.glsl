#version 330 core
// Skinned instancing: one instanced draw per (mesh piece, LOD) covers every agent that wears the
// piece at that LOD. Each instance reads its agent's palette row, written once per frame by the
// animation processor and reused by every pass (colour and shadow).
//
// Defines: DEPTH_ONLY (shadow pass: position only), UNSKINNED (the benchmark's ceiling: the same draw
// without bone fetches), SKIN_LOOP and SKIN_ONE_BONE (the benchmark's ablations: one loop over the
// four influences that stops at the first zero weight; only the first bone, at full weight).

in vec3 in_position;   // bind space
in vec4 in_normal;     // xyz bind-space normal (half floats)
in uvec4 in_joints;    // joint indices, sorted by descending weight
in vec4 in_weights;    // half floats, sorted descending, sum 1
in vec4 in_color;      // unorm8 vertex colour

in vec3 i_position;    // agent origin relative to the camera (float64 on the CPU, then float32)
in vec2 i_yaw_scale;   // heading about +Y (radians), uniform scale
in uvec2 i_palette;    // the agent's palette row: texel of its joint 0 (x = slot * J, y = texture row)
in vec4 i_tint;        // unorm8 tint

uniform mat4 u_view_proj;  // camera-relative: the camera sits at the origin
uniform sampler2D u_palette0;
uniform sampler2D u_palette1;
uniform sampler2D u_palette2;

#ifndef DEPTH_ONLY
out vec3 v_world;      // camera-relative
out vec3 v_normal;
out vec4 v_color;
#endif

void main() {
    vec4 p = vec4(in_position, 1.0);
#ifdef UNSKINNED
    vec3 skinned = in_position;
    vec3 normal = in_normal.xyz;
#else
    // The CPU hands each instance its palette texel, so no vertex pays for an integer division.
    ivec2 base = ivec2(i_palette);
#if defined(SKIN_ONE_BONE)
    ivec2 t0 = base + ivec2(int(in_joints.x), 0);
    vec4 r0 = texelFetch(u_palette0, t0, 0);
    vec4 r1 = texelFetch(u_palette1, t0, 0);
    vec4 r2 = texelFetch(u_palette2, t0, 0);
#elif defined(SKIN_LOOP)
    vec4 r0 = vec4(0.0);
    vec4 r1 = vec4(0.0);
    vec4 r2 = vec4(0.0);
    for (int i = 0; i < 4; ++i) {
        float w = in_weights[i];
        if (w == 0.0) break;
        ivec2 texel = base + ivec2(int(in_joints[i]), 0);
        r0 += w * texelFetch(u_palette0, texel, 0);
        r1 += w * texelFetch(u_palette1, texel, 0);
        r2 += w * texelFetch(u_palette2, texel, 0);
    }
#else
    // Weights are sorted: nearly every vertex of a game character has one or two influences, so the
    // first two bones are fetched unconditionally (six independent fetches the GPU can overlap) and
    // the third and fourth only where their weight is not zero.
    ivec2 t0 = base + ivec2(int(in_joints.x), 0);
    ivec2 t1 = base + ivec2(int(in_joints.y), 0);
    vec4 r0 = in_weights.x * texelFetch(u_palette0, t0, 0) + in_weights.y * texelFetch(u_palette0, t1, 0);
    vec4 r1 = in_weights.x * texelFetch(u_palette1, t0, 0) + in_weights.y * texelFetch(u_palette1, t1, 0);
    vec4 r2 = in_weights.x * texelFetch(u_palette2, t0, 0) + in_weights.y * texelFetch(u_palette2, t1, 0);
    if (in_weights.z > 0.0) {
        ivec2 t2 = base + ivec2(int(in_joints.z), 0);
        ivec2 t3 = base + ivec2(int(in_joints.w), 0);
        r0 += in_weights.z * texelFetch(u_palette0, t2, 0) + in_weights.w * texelFetch(u_palette0, t3, 0);
        r1 += in_weights.z * texelFetch(u_palette1, t2, 0) + in_weights.w * texelFetch(u_palette1, t3, 0);
        r2 += in_weights.z * texelFetch(u_palette2, t2, 0) + in_weights.w * texelFetch(u_palette2, t3, 0);
    }
#endif
    vec3 skinned = vec3(dot(r0, p), dot(r1, p), dot(r2, p));
    vec3 normal = vec3(dot(r0.xyz, in_normal.xyz), dot(r1.xyz, in_normal.xyz), dot(r2.xyz, in_normal.xyz));
#endif
    float c = cos(i_yaw_scale.x);
    float s = sin(i_yaw_scale.x);
    // Heading about +Y: the character's +Z (its front) turns toward (sin, 0, cos).
    vec3 local = vec3(c * skinned.x + s * skinned.z, skinned.y, -s * skinned.x + c * skinned.z);
    vec3 world = i_position + i_yaw_scale.y * local;
    gl_Position = u_view_proj * vec4(world, 1.0);
#ifndef DEPTH_ONLY
    v_world = world;
    v_normal = vec3(c * normal.x + s * normal.z, normal.y, -s * normal.x + c * normal.z);
    v_color = in_color * i_tint;
#endif
}
