// The packed fields of the vertex and instance records, as crowd/draw/render.py (pack_vertices,
// write_heading), crowd/draw/weapons.py and crowd/draw/town.py write them: read the same way by every
// vertex shader that draws them (skin, weapon, town).

// A heading's cos and sin, snorm16 x2 (cos in the low half).
vec2 heading_cos_sin(uint v) {
    return vec2(ivec2(uvec2(v) << uvec2(16u, 0u)) >> 16) / 32767.0;
}

// `v` turned about +Y by the heading (cos, sin): the character's +Z (its front) turns toward (sin, 0, cos).
vec3 turn_about_y(vec2 cs, vec3 v) {
    return vec3(cs.x * v.x + cs.y * v.z, v.y, -cs.y * v.x + cs.x * v.z);
}

// A normal, snorm10 x3: each field sign-extended by a shift to the top and an arithmetic shift back down.
vec3 unpack_normal(uint v) {
    return vec3(ivec3(uvec3(v) << uvec3(22u, 12u, 2u)) >> 22) / 511.0;
}

// A colour, RGBA8 (R in the low byte).
vec4 unpack_rgba8(uint v) {
    return vec4((uvec4(v) >> uvec4(0u, 8u, 16u, 24u)) & 0xFFu) / 255.0;
}
