#version 410 core
// A kept weapon: appended to each of its lists, a vertex stream each, as feedback_cull.geom.glsl does for
// the bodies (the rasterizer is off; the lists are counted after).
layout(points) in;
layout(points, max_vertices = 4) out;

flat in ivec4 v_emit[];
in vec4 v_row0[];
in vec4 v_row1[];
in vec4 v_row2[];
in vec4 v_position_scale[];
flat in uvec4 v_fields[];

// A list's instance, one block a stream (transform feedback captures "S<k>.row0" ... "S<k>.fields").
layout(stream = 0) out S0 { vec4 row0; vec4 row1; vec4 row2; vec4 position_scale; flat uvec4 fields; } s0;
layout(stream = 1) out S1 { vec4 row0; vec4 row1; vec4 row2; vec4 position_scale; flat uvec4 fields; } s1;
layout(stream = 2) out S2 { vec4 row0; vec4 row1; vec4 row2; vec4 position_scale; flat uvec4 fields; } s2;
layout(stream = 3) out S3 { vec4 row0; vec4 row1; vec4 row2; vec4 position_scale; flat uvec4 fields; } s3;

// (one line: GLSL 4.10 has no line continuation, which came with 4.20)
#define EMIT(out_block, k) if (v_emit[0][k] != 0) { out_block.row0 = v_row0[0]; out_block.row1 = v_row1[0]; out_block.row2 = v_row2[0]; out_block.position_scale = v_position_scale[0]; out_block.fields = v_fields[0]; EmitStreamVertex(k); }

#include "feedback_streams.glsl"
