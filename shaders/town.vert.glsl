#version 330 core
// The town (crowd/draw/town.py): buildings, cars, barriers and kerbs, one instanced draw per mesh. An
// instance is a placement on the ground: its origin relative to the camera (float64 on the CPU, then
// float32, as the crowd's) and its heading, which turns the mesh's +Z toward (sin, 0, cos) as an agent's
// does; its tint multiplies the vertex colours. Shares skin.frag.glsl and depth.frag.glsl with the crowd.
//
// Defines: DEPTH_ONLY (shadow pass: position only).

in vec3 in_position;
in uvec2 in_packed;     // x: normal, snorm10 x3 | y: colour, RGBA8
in vec3 i_position;     // the placement's origin, relative to the camera
in uvec2 i_fields;      // x: cos, sin of the heading, snorm16 x2 | y: tint, RGBA8

uniform mat4 u_view_proj;

#ifndef DEPTH_ONLY
out vec3 v_world;
out vec3 v_normal;
out vec4 v_color;
#endif

vec4 unpack_rgba8(uint v) {
    return vec4((uvec4(v) >> uvec4(0u, 8u, 16u, 24u)) & 0xFFu) / 255.0;
}

void main() {
    vec2 cs = vec2(ivec2(uvec2(i_fields.x) << uvec2(16u, 0u)) >> 16) / 32767.0;
    float c = cs.x;
    float s = cs.y;
    vec3 p = in_position;
    vec3 world = i_position + vec3(c * p.x + s * p.z, p.y, -s * p.x + c * p.z);
    gl_Position = u_view_proj * vec4(world, 1.0);
#ifndef DEPTH_ONLY
    vec3 n = vec3(ivec3(uvec3(in_packed.x) << uvec3(22u, 12u, 2u)) >> 22) / 511.0;
    v_world = world;
    v_normal = vec3(c * n.x + s * n.z, n.y, -s * n.x + c * n.z);
    v_color = unpack_rgba8(in_packed.y) * unpack_rgba8(i_fields.y);
#endif
}
