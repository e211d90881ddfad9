// The animation processor's maths, shared word for word by processor.comp.glsl (GL 4.3 compute) and
// processor.frag.glsl (GL 3.3 fragment path), so both paths compute the same floats.
// Its float64 twin is crowd.processor.reference_palette: change one, change the other.
//
// Defines set by crowd/processor.py: LAYERS (1..4), REST_THRESHOLD, HAS_SCALE (joint scale texture
// exists), HAS_MASKS (joint mask texture exists), MAX_JOINTS.

uniform sampler2D u_anim;        // AnimationTexture (2J, rows): texel 2j = real, 2j+1 = dual of joint j
#ifdef HAS_SCALE
uniform sampler2D u_anim_scale;  // (J, rows): uniform joint scale per frame
#endif
uniform isampler2D u_parents;    // hierarchy texture (J, 1): parent index, -1 for roots, parents first
uniform sampler2D u_clips;       // clip table (C, 1): first row, frame count, fps, loop flag
#ifdef HAS_MASKS
uniform sampler2D u_masks;       // (J, M): per-joint weight factor of mask m
#endif
uniform sampler2D u_layers;      // (LAYERS * agents_per_row, rows): clip, phase, weight, mask per layer
uniform int u_joints;
uniform int u_agents;
uniform int u_agents_per_row;
uniform int u_rest_row;

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

// Unit dual quaternion (real r, dual d, both xyzw) times a uniform scale applied first.
Affine dq_affine(vec4 r, vec4 d, float s) {
    float xx = r.x * r.x, yy = r.y * r.y, zz = r.z * r.z;
    float xy = r.x * r.y, xz = r.x * r.z, yz = r.y * r.z;
    float wx = r.w * r.x, wy = r.w * r.y, wz = r.w * r.z;
    // t = 2 * vec(d * conj(r))
    vec3 t = 2.0 * (r.w * d.xyz - d.w * r.xyz + cross(r.xyz, d.xyz));
    Affine m;
    m.r0 = vec4(s * (1.0 - 2.0 * (yy + zz)), s * 2.0 * (xy - wz), s * 2.0 * (xz + wy), t.x);
    m.r1 = vec4(s * 2.0 * (xy + wz), s * (1.0 - 2.0 * (xx + zz)), s * 2.0 * (yz - wx), t.y);
    m.r2 = vec4(s * 2.0 * (xz - wy), s * 2.0 * (yz + wx), s * (1.0 - 2.0 * (xx + yy)), t.z);
    return m;
}

float joint_scale(int joint, int row) {
#ifdef HAS_SCALE
    return texelFetch(u_anim_scale, ivec2(joint, row), 0).x;
#else
    return 1.0;
#endif
}

Affine stored_affine(int joint, int row) {
    return dq_affine(texelFetch(u_anim, ivec2(2 * joint, row), 0), texelFetch(u_anim, ivec2(2 * joint + 1, row), 0),
                     joint_scale(joint, row));
}

int parent_of(int joint) {
    return texelFetch(u_parents, ivec2(joint, 0), 0).x;
}

// One layer's local transform of one joint: the two neighbouring baked keys, lerped blindly (they are
// sign-aligned at bake time), then divided by |real| so each layer enters the blend as a unit DQ.
void sample_layer(vec4 layer, int joint, out vec4 real, out vec4 dual, out float scale) {
    vec4 info = texelFetch(u_clips, ivec2(int(layer.x), 0), 0);
    float phase = info.w > 0.5 ? fract(layer.y) : clamp(layer.y, 0.0, 1.0);
    float f = phase * (info.y - 1.0);
    float i0 = clamp(floor(f), 0.0, info.y - 2.0);
    float u = f - i0;
    int row = int(info.x + i0);
    vec4 r0 = texelFetch(u_anim, ivec2(2 * joint, row), 0);
    vec4 d0 = texelFetch(u_anim, ivec2(2 * joint + 1, row), 0);
    vec4 r1 = texelFetch(u_anim, ivec2(2 * joint, row + 1), 0);
    vec4 d1 = texelFetch(u_anim, ivec2(2 * joint + 1, row + 1), 0);
    real = r0 + (r1 - r0) * u;
    dual = d0 + (d1 - d0) * u;
    // Aligned unit keys have a non-negative dot product, so |real| >= sqrt(1/2) here.
    float inv = 1.0 / length(real);
    real *= inv;
    dual *= inv;
#ifdef HAS_SCALE
    float s0 = joint_scale(joint, row);
    scale = s0 + (joint_scale(joint, row + 1) - s0) * u;
#else
    scale = 1.0;
#endif
}

// The blended local transform of one joint of one agent (ozz-animation's blending job semantics):
// weight = max(weight, 0) * mask; signs aligned to the heaviest layer; weighted sum; normalised by the
// real part's norm. A joint whose weights add up to less than REST_THRESHOLD takes the rest pose.
Affine blended_local(int agent, int joint) {
    vec4 real[LAYERS];
    vec4 dual[LAYERS];
    float scale[LAYERS];
    float weight[LAYERS];
    int heaviest = 0;
    int base_x = (agent % u_agents_per_row) * LAYERS;
    int y = agent / u_agents_per_row;
    for (int l = 0; l < LAYERS; ++l) {
        vec4 layer = texelFetch(u_layers, ivec2(base_x + l, y), 0);
        float w = max(layer.z, 0.0);
#ifdef HAS_MASKS
        if (layer.w >= 0.0) w *= texelFetch(u_masks, ivec2(joint, int(layer.w)), 0).x;
#endif
        weight[l] = w;
        if (w > 0.0) {
            sample_layer(layer, joint, real[l], dual[l], scale[l]);  // layers that do not count cost no fetches
        } else {
            real[l] = vec4(0.0);
            dual[l] = vec4(0.0);
            scale[l] = 0.0;
        }
        if (w > weight[heaviest]) heaviest = l;
    }
    vec4 r = vec4(0.0);
    vec4 d = vec4(0.0);
    float s = 0.0;
    float total = 0.0;
    for (int l = 0; l < LAYERS; ++l) {
        float signed_w = dot(real[l], real[heaviest]) < 0.0 ? -weight[l] : weight[l];
        r += signed_w * real[l];
        d += signed_w * dual[l];
        s += weight[l] * scale[l];
        total += weight[l];
    }
    if (total < REST_THRESHOLD) return stored_affine(joint, u_rest_row);
    // Every term has a non-negative dot product with the heaviest layer's unit real part, so
    // |r| >= weight[heaviest] >= total / LAYERS: the division below never meets ~0.
    float inv = 1.0 / length(r);
    r *= inv;
    d *= inv;
    d -= r * dot(r, d);
    return dq_affine(r, d, s / total);
}
