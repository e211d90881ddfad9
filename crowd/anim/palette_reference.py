"""The float64 model of the processor on the same baked keys (``reference_palette``), which the GPU's
float32 palette is tested against, and qt_corrected's fitted nlerp weight, which both it and the
shaders use."""

from __future__ import annotations

import numpy as np

from .. import transforms as tf
from ..frame import CLIP, MASK, PHASE, WEIGHT, validate_layers, validate_masks
from . import foot_lock as lock
from .bake import AnimationBake
from .processor_inputs import DEFAULT_INTERPOLATION, check_interpolation
from .reference import CANCELLED_NORM, REST_THRESHOLD, aligned_sign

# qt_corrected's weight: nlerp at weight u' = u + u (u - 1/2) (u - 1) (1 - d) (A(d) (u - 1/2)^2 + B(d)), d the keys'
# dot product, A and B quadratics in d, turns by u times the keys' angle, as slerp does: to within 6.6e-7 rad
# of rotation for keys up to 36 degrees apart (d >= 0.95) and 1.1e-3 rad for keys a half turn apart, where
# nlerp is off by 1.0e-3 and 0.14 rad. The (1 - d) factor is the shape of nlerp's own error (it vanishes as the keys
# meet), so the fit holds its ratio to it near d = 1, where keys usually are. Fitted by weighted least
# squares, bench/slerp_fit.py; the error's maxima over (u, d) are searched in tests/test_processor.py.
SLERP_FIT = (1.007417582391, -1.563037689162, 0.556641371575, 0.848875584203, -0.236418056665, 0.054274391573)  # A's, then B's


def corrected_weight(u, d):
    """qt_corrected's nlerp weight (float64; shaders/processor_common.glsl has it in float32)."""
    d = np.clip(d, 0.0, 1.0)
    a = SLERP_FIT[0] + d * (SLERP_FIT[1] + d * SLERP_FIT[2])
    b = SLERP_FIT[3] + d * (SLERP_FIT[4] + d * SLERP_FIT[5])
    c = u - 0.5
    return u + u * c * (u - 1.0) * (1.0 - d) * (a * c * c + b)


def _translation(real: np.ndarray, dual: np.ndarray) -> np.ndarray:
    """Translation of stored DQ keys (f16 keys are not exactly unit: dq_to_rt normalises first)."""
    return tf.dq_to_rt(real, dual)[1]


def _catmull_rom(p0, p1, p2, p3, u):
    """Uniform Catmull-Rom between p1 and p2; u broadcasts against the keys' leading axes."""
    return p1 + u * (0.5 * (p2 - p0) + u * ((p0 - 2.5 * p1 + 2.0 * p2 - 0.5 * p3) + u * (0.5 * (p3 - p0) + 1.5 * (p1 - p2))))


def _frame(table, clip, phase):
    """Where each agent's layer falls in its clip, as the shader's layer_frame finds it: (the texture
    row of the key before it (N,), the share of the way to the next (N, 1, 1))."""
    first, count, _, loop = table[clip].T
    phase = np.where(loop > 0.5, phase - np.floor(phase), np.clip(phase, 0.0, 1.0))
    f = phase * (count - 1.0)
    i0 = np.clip(np.floor(f), 0.0, count - 2.0)
    return (first + i0).astype(np.int64), (f - i0)[:, None, None]


def _sample_keys(texels, scales, table, clip, phase, interpolation):
    """One layer's local transform of every joint, float64, as the shader samples it. Returns
    (rotation or DQ real (N, J, 4), translation (N, J, 3) or DQ dual (N, J, 4), scale (N, J))."""
    first, count, _, loop = table[clip].T
    looping = loop > 0.5
    row, u = _frame(table, clip, phase)

    def key(r):
        s = np.ones(texels.shape[1] // 2) if scales is None else scales[r]
        return texels[r, 0::2], texels[r, 1::2], s

    (r1, d1, s1), (r2, d2, s2) = key(row), key(row + 1)
    if interpolation == "dq_lerp":
        r = r1 + (r2 - r1) * u
        d = d1 + (d2 - d1) * u
        inv = 1.0 / np.linalg.norm(r, axis=-1, keepdims=True)
        return r * inv, d * inv, s1 + (s2 - s1) * u[..., 0]
    t1, t2 = _translation(r1, d1), _translation(r2, d2)
    if interpolation in ("qt_lerp", "qt_corrected"):
        w = corrected_weight(u, np.sum(r1 * r2, axis=-1, keepdims=True)) if interpolation == "qt_corrected" else u
        q = r1 + (r2 - r1) * w
        return q / np.linalg.norm(q, axis=-1, keepdims=True), t1 + (t2 - t1) * u, s1 + (s2 - s1) * u[..., 0]
    # qt_cubic: the outer keys wrap around a loop (its closing frame repeats frame 0, so frame 0's
    # predecessor is frame count - 2 and the closing frame's successor is frame 1) and are extrapolated
    # linearly at the ends of a one-shot clip.
    first_row = first.astype(np.int64)
    last = count.astype(np.int64) - 1
    at_start, at_end = row == first_row, row + 1 == first_row + last
    prev_row = np.where(at_start & looping, first_row + last - 1, np.maximum(row - 1, first_row))
    next_row = np.where(at_end & looping, first_row + 1, np.minimum(row + 2, first_row + last))
    r0, d0, s0 = key(prev_row)
    r3, d3, s3 = key(next_row)
    t0, t3 = _translation(r0, d0), _translation(r3, d3)
    r0 = np.where(np.sum(r0 * r1, axis=-1, keepdims=True) < 0.0, -r0, r0)
    r3 = np.where(np.sum(r3 * r2, axis=-1, keepdims=True) < 0.0, -r3, r3)
    ext_start = (at_start & ~looping)[:, None, None]
    ext_end = (at_end & ~looping)[:, None, None]
    r0, t0 = np.where(ext_start, 2.0 * r1 - r2, r0), np.where(ext_start, 2.0 * t1 - t2, t0)
    r3, t3 = np.where(ext_end, 2.0 * r2 - r1, r3), np.where(ext_end, 2.0 * t2 - t1, t3)
    s0 = np.where(ext_start[..., 0], 2.0 * s1 - s2, s0)
    s3 = np.where(ext_end[..., 0], 2.0 * s2 - s1, s3)
    q = _catmull_rom(r0, r1, r2, r3, u)
    return q / np.linalg.norm(q, axis=-1, keepdims=True), _catmull_rom(t0, t1, t2, t3, u), _catmull_rom(s0, s1, s2, s3, u[..., 0])


def reference_palette(bake: AnimationBake, layers, masks=None, interpolation: str = DEFAULT_INTERPOLATION,
                      foot_lock: lock.FootLockTwin | None = None, motion=None, dt: float = 0.0) -> np.ndarray:
    """Float64 model of the processor on the same baked keys: (N, J, 3, 4) skinning matrix rows.

    The bake's own error against the source clips is measured elsewhere (crowd.anim.accuracy, issue 7's
    report); this function isolates what the GPU adds: float32 arithmetic. With `foot_lock` (the twin
    of a processor built with legs) the frame's `motion` and `dt` advance its state as a run does.
    """
    interpolation = check_interpolation(interpolation)
    masks = validate_masks(masks, bake.joint_count)
    layers = validate_layers(layers, len(bake.clips), 0 if masks is None else masks.shape[0], np.shape(layers)[1]).astype(np.float64)
    n, lcount, _ = layers.shape
    jc = bake.joint_count
    texels = bake.texels.astype(np.float64)
    scales = None if bake.scale is None else bake.scale.astype(np.float64)
    table = bake.clip_table.astype(np.float64)
    qt = interpolation != "dq_lerp"
    real = np.zeros((lcount, n, jc, 4))
    second = np.zeros((lcount, n, jc, 3 if qt else 4))  # translation (QT) or dual part (DQ)
    scale = np.zeros((lcount, n, jc))
    weight = np.zeros((lcount, n, jc))
    # Raw weights, compared with S: the shaders scale them by a power of two near 1 / S, which changes no
    # result (power_of_two_below in processor_common.glsl), and float64 does not underflow at float32's
    # smallest weights.
    layer_sum = np.maximum(layers[:, :, WEIGHT], 0.0).sum(axis=1)[:, None]  # (N, 1)
    for l in range(lcount):
        clip = layers[:, l, CLIP].astype(np.int64)
        real[l], second[l], scale[l] = _sample_keys(texels, scales, table, clip, layers[:, l, PHASE], interpolation)
        w = np.repeat(np.maximum(layers[:, l, WEIGHT], 0.0)[:, None], jc, axis=1)
        mask = layers[:, l, MASK].astype(np.int64)
        if masks is not None:
            w = np.where(mask[:, None] >= 0, w * masks[np.maximum(mask, 0)].astype(np.float64), w)
        weight[l] = w
    real = np.where(weight[..., None] > 0, real, 0.0)
    second = np.where(weight[..., None] > 0, second, 0.0)
    scale = np.where(weight > 0, scale, 0.0)
    anchor = np.argmax(weight > 0, axis=0)  # the first layer with a weight above 0, as the shader's scan finds it
    ref = np.take_along_axis(real, anchor[None, ..., None], axis=0)[0]
    signed = aligned_sign(real, ref[None]) * weight
    r = np.sum(signed[..., None] * real, axis=0)
    cancelled = (np.linalg.norm(r, axis=-1) < CANCELLED_NORM * layer_sum)[..., None]
    r = np.where(cancelled, ref, r)
    total = weight.sum(axis=0)
    low = (total <= 0.0) | (total < REST_THRESHOLD * layer_sum)
    safe = np.where(low, 1.0, total)
    s = np.sum(weight * scale, axis=0) / safe
    rest_r = texels[bake.rest_row, 0::2]
    rest_d = texels[bake.rest_row, 1::2]
    rest_s = np.ones(jc) if scales is None else scales[bake.rest_row]
    r = np.where(low[..., None], rest_r[None], r)
    s = np.where(low, rest_s[None], s)
    if qt:
        t = np.sum(weight[..., None] * second, axis=0) / safe[..., None]
        t = np.where(low[..., None], _translation(rest_r, rest_d)[None], t)
        r = r / np.linalg.norm(r, axis=-1, keepdims=True)
        local = tf.trs_to_mat4(t, r, np.repeat(s[..., None], 3, -1))
    else:
        d = np.sum(signed[..., None] * second, axis=0)
        d = np.where(cancelled, np.take_along_axis(second, anchor[None, ..., None], axis=0)[0], d)
        d = np.where(low[..., None], rest_d[None], d)
        local = tf.dq_to_mat4(r, d, s)
    if foot_lock is not None:
        local = foot_lock.apply(local, bake.parents, motion, dt)
    glob = np.empty_like(local)
    for j, p in enumerate(bake.parents):
        glob[:, j] = local[:, j] if p < 0 else glob[:, p] @ local[:, j]
    if bake.residual is not None:  # each joint's non-uniform scale over its uniform one: its own matrix only
        glob[..., :3, :3] = glob[..., :3, :3] * _blended_residual(bake, layers, weight, low, safe)[..., None, :]
    return (glob @ bake.inverse_bind()[None])[:, :, :3, :]


def _blended_residual(bake, layers, weight, low, safe) -> np.ndarray:
    """(N, J, 3): each layer's residual lerped between its keys (linearly, whatever the interpolation),
    weighted as the scale is, the rest pose's where the weights add up to about nothing."""
    res = bake.residual.astype(np.float64)
    table = bake.clip_table.astype(np.float64)
    out = np.zeros(weight.shape[1:] + (3,))
    for l in range(layers.shape[1]):
        row, u = _frame(table, layers[:, l, CLIP].astype(np.int64), layers[:, l, PHASE])
        out += weight[l][..., None] * (res[row] + (res[row + 1] - res[row]) * u)
    out /= safe[..., None]
    return np.where(low[..., None], res[bake.rest_row][None], out)


def palette_joint_positions(palette_rows: np.ndarray, inverse_bind: np.ndarray) -> np.ndarray:
    """Model-space joint positions from skinning matrix rows (N, J, 3, 4): skin × bind, translation."""
    bind = np.linalg.inv(np.asarray(inverse_bind, dtype=np.float64))
    rows = np.asarray(palette_rows, dtype=np.float64)
    return np.einsum("njrc,jc->njr", rows, bind[:, :, 3])
