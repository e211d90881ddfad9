// The animation processor's maths, shared word for word by processor.comp.glsl (GL 4.3 compute) and
// processor.frag.glsl (GL 3.3 fragment path), so both paths compute the same floats.
// Its float64 twin is crowd.anim.processor.reference_palette: change one, change the other.
//
// Defines set by crowd/anim/processor.py: LAYERS (1..4), REST_THRESHOLD, HAS_SCALE (joint scale texture
// exists), HAS_MASKS (joint mask texture exists), MAX_JOINTS, COMPRESSED (the clips' keys are packed
// words, crowd.anim.compress, and u_anim holds only the inverse bind and rest rows), and the interpolation:
// none (dq_lerp), INTERPOLATION_QT (qt_lerp), INTERPOLATION_QT with INTERPOLATION_CORRECTED and its SLERP_FIT_A and
// SLERP_FIT_B (qt_corrected), or INTERPOLATION_QT with INTERPOLATION_CUBIC (qt_cubic).

uniform sampler2D u_anim;        // AnimationTexture (2J, rows): texel 2j = real, 2j+1 = dual of joint j
#ifdef COMPRESSED
uniform usampler2D u_keys;       // packed key words, u_key_width a row (crowd.anim.compress)
uniform usampler2D u_tracks;     // (4J, clips): four RGBA32UI texels of track headers per (clip, joint)
uniform int u_key_width;
#endif
#ifdef HAS_SCALE
uniform sampler2D u_anim_scale;  // (J, rows): uniform joint scale per frame
#endif
#if defined(HAS_RESIDUAL) && !defined(RESIDUAL_PLANE)
uniform sampler2D u_anim_residual;  // (J, rows): xyz each joint's non-uniform scale over its uniform one (own matrix only)
uniform uint u_residual_joints[8];  // a bit a joint: those whose scale is non-uniform somewhere (the others fetch none)

bool has_residual(int joint) {
    return ((u_residual_joints[joint >> 5] >> uint(joint & 31)) & 1u) != 0u;
}
#endif
// Where the residual is blended: the fragment path's locals pass blends it with the local transform
// (RESIDUAL_IN_BLEND) and hands it to the compose pass in a fourth plane (RESIDUAL_PLANE: that pass reads
// no residual texture); the compute path blends it after the chain walk (blended_residual), which the
// H200 ran faster than carrying it across the barrier.
#ifdef RESIDUAL_IN_BLEND
#define ScaleKey vec4  // xyz the residual, w the uniform scale
bool g_has_residual;   // the joint being blended has one
vec3 g_residual;       // which blended_local leaves here beside the local it returns
#else
#define ScaleKey float
#endif
uniform isampler2D u_parents;    // hierarchy texture (J, 1): parent index, -1 for roots, parents first
uniform sampler2D u_clips;       // clip table (C, 1): first row, frame count, fps, loop flag
#ifdef HAS_MASKS
uniform sampler2D u_masks;       // (J, M): per-joint weight factor of mask m
#endif
#ifdef LAYERS_BUFFER
// The compute path reads the layers where the AI (or the upload) wrote them: no copy into a texture.
layout(std430, binding = LAYERS_BUFFER) readonly buffer LayersIn { vec4 layers_in[]; };  // agent * LAYERS + layer: clip, phase, weight, mask
#else
uniform sampler2D u_layers;      // (LAYERS * u_layer_agents_per_row, rows): clip, phase, weight, mask per layer
uniform int u_layer_agents_per_row;  // agents side by side in a row of u_layers
#endif
uniform int u_joints;            // this character's joints
uniform int u_agents;            // this character's agents, u_first_agent on (a dispatch or draw per character)
uniform int u_first_agent;
uniform int u_agents_per_row;    // this character's agents side by side in a palette row
uniform int u_rest_row;        // the rest pose's row of u_anim
uniform int u_rest_scale_row;  // and of u_anim_scale (a compressed bake's u_anim has two rows only)

// Rows of an affine 3x4 matrix.
struct Affine {
    vec4 r0;
    vec4 r1;
    vec4 r2;
};

// a ∘ b: apply b first, then a.
Affine compose(Affine a, Affine b) {
    Affine m;
    m.r0 = a.r0.x * b.r0 + a.r0.y * b.r1 + a.r0.z * b.r2 + vec4(0.0, 0.0, 0.0, a.r0.w);
    m.r1 = a.r1.x * b.r0 + a.r1.y * b.r1 + a.r1.z * b.r2 + vec4(0.0, 0.0, 0.0, a.r1.w);
    m.r2 = a.r2.x * b.r0 + a.r2.y * b.r1 + a.r2.z * b.r2 + vec4(0.0, 0.0, 0.0, a.r2.w);
    return m;
}

// Rotation (unit quaternion q, xyzw), then translation t, with a uniform scale applied first.
Affine qt_affine(vec4 r, vec3 t, float s) {
    float xx = r.x * r.x, yy = r.y * r.y, zz = r.z * r.z;
    float xy = r.x * r.y, xz = r.x * r.z, yz = r.y * r.z;
    float wx = r.w * r.x, wy = r.w * r.y, wz = r.w * r.z;
    Affine m;
    m.r0 = vec4(s * (1.0 - 2.0 * (yy + zz)), s * 2.0 * (xy - wz), s * 2.0 * (xz + wy), t.x);
    m.r1 = vec4(s * 2.0 * (xy + wz), s * (1.0 - 2.0 * (xx + zz)), s * 2.0 * (yz - wx), t.y);
    m.r2 = vec4(s * 2.0 * (xz - wy), s * 2.0 * (yz + wx), s * (1.0 - 2.0 * (xx + yy)), t.z);
    return m;
}

// The translation of a dual quaternion with unit real part: 2 * vec(d * conj(r)).
vec3 dq_translation(vec4 r, vec4 d) {
    return 2.0 * (r.w * d.xyz - d.w * r.xyz + cross(r.xyz, d.xyz));
}

// Unit dual quaternion (real r, dual d, both xyzw) times a uniform scale applied first.
Affine dq_affine(vec4 r, vec4 d, float s) {
    return qt_affine(r, dq_translation(r, d), s);
}

float uniform_scale(int joint, int row) {
#ifdef HAS_SCALE
    return texelFetch(u_anim_scale, ivec2(joint, row), 0).x;
#else
    return 1.0;
#endif
}

ScaleKey joint_scale(int joint, int row) {
#ifdef RESIDUAL_IN_BLEND
    vec3 residual = g_has_residual ? texelFetch(u_anim_residual, ivec2(joint, row), 0).xyz : vec3(1.0);
    return vec4(residual, uniform_scale(joint, row));
#else
    return uniform_scale(joint, row);
#endif
}

// A scale key's uniform part (what runs down the chain).
float uniform_part(ScaleKey s) {
#ifdef RESIDUAL_IN_BLEND
    return s.w;
#else
    return s;
#endif
}

// A stored key as it is (the inverse bind pose in row 0, the rest pose in row u_rest_row), made unit
// first: f16 keys are unit only to within about 1e-3, which at 1 m from the origin is a millimetre.
Affine stored_affine(int joint, int row, int scale_row) {
    vec4 r = texelFetch(u_anim, ivec2(2 * joint, row), 0);
    float inv = 1.0 / length(r);
    return dq_affine(r * inv, texelFetch(u_anim, ivec2(2 * joint + 1, row), 0) * inv, uniform_scale(joint, scale_row));
}

int parent_of(int joint) {
    return texelFetch(u_parents, ivec2(joint, 0), 0).x;
}

#ifdef COMPRESSED
uint key_word(int index) {
    int y = index / u_key_width;
    return texelFetch(u_keys, ivec2(index - y * u_key_width, y), 0).x;
}

// Field `bit` (< 64) of `bits` (1..20) bits of the 64-bit value hi:lo.
uint key_field(uint lo, uint hi, int bit, uint mask) {
    if (bit >= 32) return (hi >> uint(bit - 32)) & mask;
    uint low_part = lo >> uint(bit);
    return (bit == 0 ? low_part : low_part | (hi << uint(32 - bit))) & mask;
}

// Key `key` of a track: its three components low + k * step, the k packed `bits` bits each after
// `lead` bits (2 where each key names its own dropped component, in `index`; else 0), key after key
// from the track's first word (crowd.anim.compress's format).
vec3 track_key(uvec4 low, uvec4 step, uint meta, int key, int lead, out uint index) {
    int bits = int(meta & 31u);
    vec3 v = uintBitsToFloat(low.xyz);
    index = 0u;
    if (bits == 0) return v;  // a constant track
    int key_bits = 3 * bits + lead;
    int bit = key * key_bits;
    int word = int(meta >> 8u) + (bit >> 5);
    int shift = bit & 31;
    uint w0 = key_word(word);
    uint w1 = key_word(word + 1);
    uint lo = shift == 0 ? w0 : (w0 >> uint(shift)) | (w1 << uint(32 - shift));
    uint hi = w1 >> uint(shift);
    if (shift + key_bits > 64) hi |= key_word(word + 2) << uint(32 - shift);  // shift >= 2 here
    uint mask = (1u << uint(bits)) - 1u;
    index = lo & 3u;
    uvec3 k = uvec3(key_field(lo, hi, lead, mask), key_field(lo, hi, lead + bits, mask), key_field(lo, hi, lead + 2 * bits, mask));
    return v + vec3(k) * uintBitsToFloat(step.xyz);
}

// One (clip, joint)'s track headers, fetched once per layer sample for all the keys it reads.
struct Tracks {
    uvec4 rotation_low;   // low xyz, meta
    uvec4 rotation_step;  // step xyz, the translation's meta
    uvec4 translation_low;
    uvec4 translation_step;  // fetched only where the translation moves
};

Tracks clip_tracks(int clip, int joint) {
    Tracks h;
    h.rotation_low = texelFetch(u_tracks, ivec2(4 * joint, clip), 0);
    h.rotation_step = texelFetch(u_tracks, ivec2(4 * joint + 1, clip), 0);
    h.translation_low = texelFetch(u_tracks, ivec2(4 * joint + 2, clip), 0);
    h.translation_step = (h.rotation_step.w & 31u) == 0u ? uvec4(0u) : texelFetch(u_tracks, ivec2(4 * joint + 3, clip), 0);
    return h;
}

// Key `key` of a joint's tracks: its rotation (unit, the dropped component rebuilt >= 0) and translation.
void compressed_key(Tracks h, int key, out vec4 r, out vec3 t) {
    uint drop = (h.rotation_low.w >> 5u) & 7u;
    uint own;
    vec3 v = track_key(h.rotation_low, h.rotation_step, h.rotation_low.w, key, drop == PER_KEY ? 2 : 0, own);
    if (drop == PER_KEY) drop = own;
    float c = sqrt(max(1.0 - dot(v, v), 0.0));
    r = drop == 3u ? vec4(v, c) : drop == 2u ? vec4(v.xy, c, v.z) : drop == 1u ? vec4(v.x, c, v.yz) : vec4(c, v);
    r *= inversesqrt(dot(r, r));
    t = track_key(h.translation_low, h.translation_step, h.rotation_step.w, key, 0, own);  // a constant track reads no words
}
#else
struct Tracks {
    int none;  // an uncompressed bake reads its keys by texture row
};

Tracks clip_tracks(int clip, int joint) {
    Tracks h;
    h.none = 0;
    return h;
}
#endif

// Key `key` (at texture row `row` of an uncompressed bake) of joint `joint`, whose clip's headers are
// `h`, as a dual quaternion (real, dual): stored as it is, or rebuilt from a compressed key.
void key_dq(Tracks h, int joint, int row, int key, out vec4 r, out vec4 d) {
#ifdef COMPRESSED
    vec3 t;
    compressed_key(h, key, r, t);
    d = 0.5 * vec4(t.x * r.w + t.y * r.z - t.z * r.y, -t.x * r.z + t.y * r.w + t.z * r.x, t.x * r.y - t.y * r.x + t.z * r.w, -dot(t, r.xyz));
#else
    r = texelFetch(u_anim, ivec2(2 * joint, row), 0);
    d = texelFetch(u_anim, ivec2(2 * joint + 1, row), 0);
#endif
}

#ifdef INTERPOLATION_QT
// The same key as rotation and translation; f16 keys are not exactly unit, hence the division by |r|^2.
void key_rt(Tracks h, int joint, int row, int key, out vec4 r, out vec3 t) {
#ifdef COMPRESSED
    compressed_key(h, key, r, t);
#else
    r = texelFetch(u_anim, ivec2(2 * joint, row), 0);
    t = dq_translation(r, texelFetch(u_anim, ivec2(2 * joint + 1, row), 0)) / dot(r, r);
#endif
}
#endif

#ifdef INTERPOLATION_CORRECTED
// qt_corrected's nlerp weight (crowd.anim.processor.corrected_weight says how it was fitted): u moved so
// that nlerp between keys with dot product d turns by u times their angle, as slerp does.
float corrected_weight(float u, float d) {
    d = clamp(d, 0.0, 1.0);
    float a = SLERP_FIT_A.x + d * (SLERP_FIT_A.y + d * SLERP_FIT_A.z);
    float b = SLERP_FIT_B.x + d * (SLERP_FIT_B.y + d * SLERP_FIT_B.z);
    float c = u - 0.5;
    return u + u * c * (u - 1.0) * (1.0 - d) * (a * c * c + b);
}
#endif

#ifdef INTERPOLATION_CUBIC
// Uniform Catmull-Rom between p1 and p2 (Horner form, the same as crowd.anim.processor._catmull_rom).
vec4 catmull_rom(vec4 p0, vec4 p1, vec4 p2, vec4 p3, float u) {
    return p1 + u * (0.5 * (p2 - p0) + u * ((p0 - 2.5 * p1 + 2.0 * p2 - 0.5 * p3) + u * (0.5 * (p3 - p0) + 1.5 * (p1 - p2))));
}
#endif

// One layer's local transform of one joint from its neighbouring baked keys (they are sign-aligned
// at bake time, so they lerp blindly). dq_lerp: real and dual parts lerped, then divided by |real|;
// `second` is the dual part. qt_lerp / qt_cubic: each key split into rotation and translation, the
// rotation nlerped (or Catmull-Rom'd) and made unit, the translation lerped; `second` is (t, 0).
// Where a layer's phase falls in its clip: the clip's table entry `info`, the key before it (its row is
// info.x + key) and, returned, the share of the way to the next key.
float layer_frame(vec4 layer, out vec4 info, out int key) {
    info = texelFetch(u_clips, ivec2(int(layer.x), 0), 0);
    float phase = info.w > 0.5 ? fract(layer.y) : clamp(layer.y, 0.0, 1.0);
    float f = phase * (info.y - 1.0);
    float i0 = clamp(floor(f), 0.0, info.y - 2.0);
    key = int(i0);
    return f - i0;
}

// A layer's weight for `joint`: its weight times `unit` (power_of_two_below), times its mask's entry.
float layer_weight(vec4 layer, int joint, float unit) {
    float w = max(layer.z, 0.0) * unit;
#ifdef HAS_MASKS
    if (layer.w >= 0.0) w *= texelFetch(u_masks, ivec2(joint, int(layer.w)), 0).x;
#endif
    return w;
}

void sample_layer(vec4 layer, int joint, out vec4 real, out vec4 second, out ScaleKey scale) {
    int clip = int(layer.x);
    vec4 info;
    int key;
    float u = layer_frame(layer, info, key);
    bool looping = info.w > 0.5;
    int row = int(info.x) + key;
    ScaleKey s1 = joint_scale(joint, row);
    ScaleKey s2 = joint_scale(joint, row + 1);
#if !defined(INTERPOLATION_QT)
    vec4 r1, d1, r2, d2;
    Tracks tracks = clip_tracks(clip, joint);
    key_dq(tracks, joint, row, key, r1, d1);
    key_dq(tracks, joint, row + 1, key + 1, r2, d2);
#ifdef COMPRESSED
    if (dot(r1, r2) < 0.0) {  // compressed keys carry the sign of their rebuilt component, not the track's
        r2 = -r2;
        d2 = -d2;
    }
#endif
    real = r1 + (r2 - r1) * u;
    // Aligned unit keys have a non-negative dot product, so |real| >= sqrt(1/2) here.
    float inv = 1.0 / length(real);
    real *= inv;
    second = (d1 + (d2 - d1) * u) * inv;
    scale = s1 + (s2 - s1) * u;
#else
    vec4 r1, r2;
    vec3 t1, t2;
    Tracks tracks = clip_tracks(clip, joint);
    key_rt(tracks, joint, row, key, r1, t1);
    key_rt(tracks, joint, row + 1, key + 1, r2, t2);
#ifdef COMPRESSED
    if (dot(r1, r2) < 0.0) r2 = -r2;  // compressed keys carry the sign of their rebuilt component, not the track's
#endif
#ifdef INTERPOLATION_CUBIC
    // The outer keys: around a loop, frame 0's predecessor is frame count - 2 (the closing frame
    // repeats frame 0) and the closing frame's successor is frame 1; a one-shot clip extrapolates.
    int first = int(info.x);
    int last = int(info.y) - 1;
    bool at_start = key == 0;
    bool at_end = key + 1 == last;
    int prev_key = at_start ? (looping ? last - 1 : key) : key - 1;
    int next_key = at_end ? (looping ? 1 : key + 1) : key + 2;
    vec4 r0, r3;
    vec3 t0, t3;
    key_rt(tracks, joint, first + prev_key, prev_key, r0, t0);
    key_rt(tracks, joint, first + next_key, next_key, r3, t3);
    float s0 = uniform_scale(joint, first + prev_key);  // (the residual is lerped: its outer keys are not read)
    float s3 = uniform_scale(joint, first + next_key);
    // Keys across the loop seam may hold the other sign (a joint that spins a full turn).
    if (dot(r0, r1) < 0.0) r0 = -r0;
    if (dot(r3, r2) < 0.0) r3 = -r3;
    if (at_start && !looping) {
        r0 = 2.0 * r1 - r2;
        t0 = 2.0 * t1 - t2;
        s0 = 2.0 * uniform_part(s1) - uniform_part(s2);
    }
    if (at_end && !looping) {
        r3 = 2.0 * r2 - r1;
        t3 = 2.0 * t2 - t1;
        s3 = 2.0 * uniform_part(s2) - uniform_part(s1);
    }
    real = catmull_rom(r0, r1, r2, r3, u);
    vec4 ts = catmull_rom(vec4(t0, s0), vec4(t1, uniform_part(s1)), vec4(t2, uniform_part(s2)), vec4(t3, s3), u);  // translation, uniform scale
    second = vec4(ts.xyz, 0.0);
#ifdef RESIDUAL_IN_BLEND
    scale = vec4(s1.xyz + (s2.xyz - s1.xyz) * u, ts.w);  // (the residual lerped whatever the interpolation)
#else
    scale = ts.w;
#endif
#else
#ifdef INTERPOLATION_CORRECTED
    real = r1 + (r2 - r1) * corrected_weight(u, dot(r1, r2));  // nlerp that turns as slerp does
#else
    real = r1 + (r2 - r1) * u;
#endif
    second = vec4(t1 + (t2 - t1) * u, 0.0);
    scale = s1 + (s2 - s1) * u;
#endif
    real *= 1.0 / length(real);
#endif
}

// +1 or -1: the sign that puts q in the anchor's hemisphere. Exactly on its edge (dot 0, as for keys
// (1, 0, 0, 0) against an anchor (0, 0, 0, 1)) the first non-zero of w, x, y, z decides, so that q and -q,
// the same rotation, always get opposite signs and add up instead of cancelling: the signs of w, x, y
// and z weigh 8, 4, 2 and 1, so the first non-zero one outweighs all after it, without a branch.
float aligned_sign(vec4 q, vec4 anchor) {
    float d = dot(q, anchor);
    if (d == 0.0) d = dot(sign(q), vec4(4.0, 2.0, 1.0, 8.0));
    return d < 0.0 ? -1.0 : 1.0;
}

// A power of two p with S * p in [1, 2) (S > 0 and normal; 0 gives 1). Weights are scaled by it so that
// weights of 1e-30 cannot underflow the squared norm of their sum (normalising that gave NaN), and by a
// power of two rather than 1 / S because multiplying by one is exact: the sums and ratios below round
// as those of the unscaled weights do. (Dividing by S broke the bit-for-bit agreement of the compute and
// fragment paths on an H200: 1.3e-6 apart.)
float power_of_two_below(float s) {
    uint biased = floatBitsToUint(s) >> 23;
    return s > 0.0 ? uintBitsToFloat((254u - min(biased, 253u)) << 23) : 1.0;
}

// The blended local transform of one joint of one agent (crowd.anim.reference.blend's rules, whose
// docstring says why): weight = max(weight, 0) * mask; signs aligned to the anchor, the first layer
// with a weight above 0 at this joint (the heaviest layer made the blend jump where the heaviest
// changed); weighted sum, normalised. A joint whose masked weights add up to less than REST_THRESHOLD
// times S, the sum of every layer's max(weight, 0), takes the rest pose.
// An agent's layers (clip, phase, weight, mask) and S, the sum of their max(weight, 0).
float agent_layers(int agent, out vec4 layer[LAYERS]) {
#ifndef LAYERS_BUFFER
    int base_x = (agent % u_layer_agents_per_row) * LAYERS;
    int y = agent / u_layer_agents_per_row;
#endif
    float layer_sum = 0.0;
    for (int l = 0; l < LAYERS; ++l) {
#ifdef LAYERS_BUFFER
        layer[l] = layers_in[agent * LAYERS + l];
#else
        layer[l] = texelFetch(u_layers, ivec2(base_x + l, y), 0);
#endif
        layer_sum += max(layer[l].z, 0.0);
    }
    return layer_sum;
}

#ifdef IMPOSTOR_KEY
// What an agent's impostor shows (crowd/draw/impostors.py): the clip and phase of its heaviest layer,
// the first of equals (an impostor shows one clip: its atlas holds each clip's frames, not their blends);
// (-1, 0) where no layer weighs anything (the rest pose).
vec4 impostor_key(int agent) {
    vec4 layer[LAYERS];
    agent_layers(agent, layer);
    vec4 key = vec4(-1.0, 0.0, 0.0, 0.0);
    float heaviest = 0.0;
    for (int l = 0; l < LAYERS; ++l) {
        if (layer[l].z > heaviest) {
            heaviest = layer[l].z;
            key.xy = layer[l].xy;
        }
    }
    return key;
}
#endif

#if defined(HAS_RESIDUAL) && !defined(RESIDUAL_IN_BLEND) && !defined(RESIDUAL_PLANE)
// The joint's non-uniform scale over its uniform one, blended as its scale is (each layer's lerped
// between its keys, linearly whatever the interpolation), the rest pose's where the weights add up to
// about nothing: applied to the joint's own skinning matrix only (crowd/anim/bake.py).
vec3 blended_residual(int agent, int joint) {
    if (!has_residual(joint)) return vec3(1.0);
    vec4 layer[LAYERS];
    float layer_sum = agent_layers(agent, layer);
    float unit = power_of_two_below(layer_sum);
    layer_sum *= unit;
    vec3 sum = vec3(0.0);
    float total = 0.0;
    for (int l = 0; l < LAYERS; ++l) {
        float w = layer_weight(layer[l], joint, unit);
        if (w > 0.0) {
            vec4 info;
            int key;
            float u = layer_frame(layer[l], info, key);
            int row = int(info.x) + key;
            vec3 r1 = texelFetch(u_anim_residual, ivec2(joint, row), 0).xyz;
            vec3 r2 = texelFetch(u_anim_residual, ivec2(joint, row + 1), 0).xyz;
            sum += w * (r1 + (r2 - r1) * u);
            total += w;
        }
    }
    if (!(total > 0.0) || total < REST_THRESHOLD * layer_sum) return texelFetch(u_anim_residual, ivec2(joint, u_rest_scale_row), 0).xyz;
    return sum / total;
}

#endif

#ifdef HAS_RESIDUAL
// `m` with a scale along its own axes applied first (its columns scaled).
Affine scaled_axes(Affine m, vec3 s) {
    return Affine(m.r0 * vec4(s, 1.0), m.r1 * vec4(s, 1.0), m.r2 * vec4(s, 1.0));
}
#endif

Affine blended_local(int agent, int joint) {
    vec4 real[LAYERS];
    vec4 second[LAYERS];  // dual parts (dq_lerp) or translations (qt_*)
    ScaleKey scale[LAYERS];
    float weight[LAYERS];
    vec4 layer[LAYERS];
    float layer_sum = agent_layers(agent, layer);
    float unit = power_of_two_below(layer_sum);
    layer_sum *= unit;
    float total = 0.0;
#ifdef RESIDUAL_IN_BLEND
    g_has_residual = has_residual(joint);
#endif
    for (int l = 0; l < LAYERS; ++l) {
        float w = layer_weight(layer[l], joint, unit);
        weight[l] = w;
        total += w;
        if (w > 0.0) {
            sample_layer(layer[l], joint, real[l], second[l], scale[l]);  // layers that do not count cost no fetches
        } else {
            real[l] = vec4(0.0);
            second[l] = vec4(0.0);
            scale[l] = ScaleKey(0.0);
        }
    }
    if (!(total > 0.0) || total < REST_THRESHOLD * layer_sum) {
#ifdef RESIDUAL_IN_BLEND
        g_residual = joint_scale(joint, u_rest_scale_row).xyz;
#endif
        return stored_affine(joint, u_rest_row, u_rest_scale_row);
    }
    // The anchor's parts, picked last to first with constant indices: no array is indexed by a value
    // known only at run time, which would put the arrays in slow local memory.
    vec4 anchor_real = real[LAYERS - 1];
    vec4 anchor_second = second[LAYERS - 1];
    for (int l = LAYERS - 2; l >= 0; --l) {
        if (weight[l] > 0.0) {
            anchor_real = real[l];
            anchor_second = second[l];
        }
    }
    vec4 r = vec4(0.0);
    vec4 d = vec4(0.0);
    ScaleKey s = ScaleKey(0.0);
    for (int l = 0; l < LAYERS; ++l) {
        float signed_w = aligned_sign(real[l], anchor_real) * weight[l];
        r += signed_w * real[l];
#ifdef INTERPOLATION_QT
        d += weight[l] * second[l];  // translations: a weighted mean
#else
        d += signed_w * second[l];
#endif
        s += weight[l] * scale[l];
    }
    // Every aligned term has a non-negative dot product with the anchor's unit real part, so
    // |r| >= weight[anchor] > 0. That can still be tiny (an anchor at 1e-30 of S, the other layers
    // nearly opposite one another at 90° from it): below CANCELLED_NORM times S the sum is rounding
    // noise and the blend takes the anchor's rotation, never an underflowed normalisation (NaN).
    float norm = length(r);
    if (norm < CANCELLED_NORM * layer_sum) {
        r = anchor_real;
#if !defined(INTERPOLATION_QT)
        d = anchor_second;
#endif
        norm = 1.0;
    }
    float inv = 1.0 / norm;
    r *= inv;
#ifdef RESIDUAL_IN_BLEND
    g_residual = s.xyz / total;
#endif
#ifdef INTERPOLATION_QT
    return qt_affine(r, d.xyz / total, uniform_part(s) / total);
#else
    d *= inv;
    d -= r * dot(r, d);
    return dq_affine(r, d, uniform_part(s) / total);
#endif
}
