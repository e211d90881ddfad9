#version 410 core
// Compaction without compute shaders: an agent the vertex shader put in a list is emitted on that list's
// vertex stream, which transform feedback appends to the list's buffer (in agent order). One draw fills
// up to 4 lists, one stream each (GL 4.0): on the H200 a feedback draw costs about 5 ns an agent whatever
// it writes, so four lists a draw cost what one did. The rasterizer is off; the lists are counted after,
// from what each stream wrote (feedback_count.vert.glsl).
layout(points) in;
layout(points, max_vertices = 4) out;

flat in ivec4 v_emit[];
flat in uvec4 v_entry[];

// A list's entry, one block a stream (transform feedback captures "S<k>.entry").
layout(stream = 0) out S0 { flat uint entry; } s0;
layout(stream = 1) out S1 { flat uint entry; } s1;
layout(stream = 2) out S2 { flat uint entry; } s2;
layout(stream = 3) out S3 { flat uint entry; } s3;

// The entry on stream `k`, through block `out_block`, where the agent is in that list.
// (one line: GLSL 4.10 has no line continuation, which came with 4.20)
#define EMIT(out_block, k) if (v_emit[0][k] != 0) { out_block.entry = v_entry[0][k]; EmitStreamVertex(k); }

#include "feedback_streams.glsl"
