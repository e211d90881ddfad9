"""The float64 reference: exact joint and skinning matrices straight from the source keys.

No baking, no dual quaternions, no float32: every later numeric claim (the bake's error, the GPU
processor's error, the weapon's error) is measured against this module.

Definitions (shared with the processor, so the two can be compared). Sampling one clip is the asset's
own semantics (crowd.asset.pose, re-exported here so the reference is one namespace):
- a clip is sampled at ``time = clip.start + phase * clip.duration``; looping clips wrap phase into
  [0, 1) in float64, one-shot clips clamp it to [0, 1];
- keys are interpolated as glTF says: LINEAR lerps translation/scale and slerps rotation, STEP holds,
  CUBICSPLINE is the Hermite spline of the spec (rotations renormalised);
- joints a clip does not animate keep their rest transform;
- layers blend per joint, like ozz-animation's blending job: a layer's weight is ``max(weight, 0)``
  divided by the sum S of every layer's ``max(weight, 0)`` (only ratios of weights matter), times its
  joint mask; rotations are sign-aligned to the anchor (below) and normalised after a weighted sum;
  translations and scales are weighted means;
- rest fallback: a joint whose masked weights add up to less than ``REST_THRESHOLD`` of S (the layers'
  weights before the masks) takes its rest transform. Relative, so (2e-7, 3e-7) blends as (2, 3)
  does (an absolute 1e-6 gave the rest pose for the first). S leaves the masks out on purpose:
  relative to the masked weights themselves a joint would fall back only at exactly 0; relative to
  the layer weights, a joint that every layer's mask leaves (almost) out, say a leg under
  upper-body-only layers, takes its rest pose. Negative weights count as 0 in S too, as everywhere
  (a layer at -5 changes nothing, the threshold included);
- the anchor: each joint's rotations are sign-aligned to the first-listed layer whose (masked) weight
  there is above 0. Aligning to the heaviest layer made the blend jump where the heaviest layer
  changed (0°, +120° and -120° at weights 1, 1 and 1: 1e-4 more on the second layer turned a 0.9 m
  arm by 120°, its tip by 1.56 m). With the anchor, a sign depends on the weights only through which
  layer is the first above 0, so the blend is Lipschitz in the weights: a point at R from the joint
  moves at most 2 R dw / |aligned sum| (to first order, dw a change of one layer's masked weight),
  and the aligned sum is at least the anchor's weight. That holds everywhere except where the
  anchor's own weight reaches or leaves 0. No rule does without a jump somewhere: blending each pair
  of those three layers the short way round winds a full turn around the triangle of weights, and a
  full turn cannot be filled in continuously (SO(3) is not simply connected). The anchor puts the jump
  where a layer switches on or off, the heaviest layer put it in the middle of cross-fades. The price:
  a light anchor still decides the hemisphere, so heavy layers close to each other but near 180° from
  it can be blended the long way round (the heaviest layer kept those short), and the bound grows as
  the anchor's weight shrinks. With two layers the two rules agree; they differ only where three or
  more layers are spread so that no choice of signs keeps every pair within 180°, which happens
  nowhere in the built-in zombie's clips (every pair of its local rotations is within 168°);
- a rotation exactly on the edge of the anchor's hemisphere (dot product 0) is signed by its first
  non-zero component (``aligned_sign``), so that q and -q never cancel; where the aligned sum is still
  shorter than ``CANCELLED_NORM`` (S being 1) it is rounding noise, and the blend takes the anchor's
  rotation: a valid rotation where float32 normalised an underflowed sum into NaN.
"""

from __future__ import annotations

import numpy as np

from ..asset.model import ModelError, Skeleton
from ..asset.pose import LocalPose, global_matrices, phase_to_time, rest_pose, sample_channel, sample_clip
from ..transforms import quat_normalize

__all__ = ["CANCELLED_NORM", "REST_THRESHOLD", "LocalPose", "aligned_sign", "blend", "global_matrices", "phase_to_time", "pose",
           "rest_pose", "sample_channel", "sample_clip", "skin_points", "skinning_matrices"]

REST_THRESHOLD = 1e-6  # a share of the layers' summed weight (see the module docstring)
# Length below which an aligned rotation sum (weights summing to 1) counts as cancelled: it is at least
# the anchor's weight, so only an anchor below 1e-15 of S with the other layers nearly opposite one
# another gets here. Its square is well above float32's smallest normal, 1.2e-38: the shaders never
# normalise an underflowed sum (which gave NaN).
CANCELLED_NORM = 1e-15


def aligned_sign(q: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """±1 per quaternion (…, 4): the sign that puts q in the anchor's hemisphere. On its edge (dot
    exactly 0, as for keys (1, 0, 0, 0) against an anchor (0, 0, 0, 1)) the first non-zero of w, x, y, z
    decides, so that q and -q, the same rotation, get opposite signs and add up rather than cancel."""
    d = np.sum(q * anchor, axis=-1)
    wxyz = q[..., [3, 0, 1, 2]]
    first = np.take_along_axis(wxyz, np.argmax(wxyz != 0.0, axis=-1)[..., None], axis=-1)[..., 0]
    return np.where(np.where(d == 0.0, first, d) < 0.0, -1.0, 1.0)


def blend(skeleton: Skeleton, poses: list[LocalPose], weights, masks=None) -> LocalPose:
    """Blend L layer poses with weights (L, P) and optional per-joint masks (L, J) in [0, 1]."""
    if not poses:
        raise ModelError("blend needs at least one layer")
    count = poses[0].rotation.shape[0]
    j = skeleton.joint_count
    w = np.asarray(weights, dtype=np.float64).reshape(len(poses), -1)
    if w.shape[1] == 1 and count > 1:
        w = np.repeat(w, count, axis=1)
    if not np.all(np.isfinite(w)):
        raise ModelError("blend weights hold NaN or Inf")
    w = np.maximum(w, 0.0)
    layer_sum = w.sum(axis=0)  # (P,): S, the weights that count, before the masks
    w = (w / np.where(layer_sum > 0.0, layer_sum, 1.0))[:, :, None]  # (L, P, 1), summing to 1 (or all 0)
    if masks is not None:
        m = np.clip(np.asarray(masks, dtype=np.float64).reshape(len(poses), 1, j), 0.0, 1.0)
        w = w * m  # (L, P, J)
    else:
        w = np.broadcast_to(w, (len(poses), count, j))
    total = w.sum(axis=0)  # (P, J): the joint's share of S
    low = total < REST_THRESHOLD
    q = np.stack([p.rotation for p in poses])  # (L, P, J, 4)
    anchor = np.argmax(w > 0.0, axis=0)  # (P, J): the first layer with a weight above 0 (0 where none: rest)
    ref = np.take_along_axis(q, anchor[None, :, :, None], axis=0)[0]
    sign = aligned_sign(q, ref[None])
    safe_total = np.where(low, 1.0, total)
    summed = np.sum((w * sign)[..., None] * q, axis=0)
    cancelled = np.linalg.norm(summed, axis=-1, keepdims=True) < CANCELLED_NORM
    rot = quat_normalize(np.where(cancelled, ref, summed))
    tr = np.sum(w[..., None] * np.stack([p.translation for p in poses]), axis=0) / safe_total[..., None]
    sc = np.sum(w[..., None] * np.stack([p.scale for p in poses]), axis=0) / safe_total[..., None]
    rest = rest_pose(skeleton, count)
    low = low[..., None]
    return LocalPose(np.where(low, rest.translation, tr), np.where(low, rest.rotation, rot), np.where(low, rest.scale, sc))


def skinning_matrices(skeleton: Skeleton, local: LocalPose) -> np.ndarray:
    """Joint matrices times inverse bind (P, J, 4, 4): what a vertex shader multiplies bind-space positions by."""
    return global_matrices(skeleton, local) @ skeleton.inverse_bind[None]


def pose(skeleton: Skeleton, layers, masks=None) -> LocalPose:
    """Convenience: ``layers`` is a list of (clip, phases, weights); returns the blended local pose."""
    sampled = [sample_clip(skeleton, clip, phases) for clip, phases, _ in layers]
    return blend(skeleton, sampled, [np.atleast_1d(np.asarray(w, dtype=np.float64)) for _, _, w in layers], masks)


def skin_points(matrices: np.ndarray, positions: np.ndarray, joints: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Linear-blend skinning of bind-space points with (P, J, 4, 4) matrices → (P, V, 3), float64."""
    pos = np.asarray(positions, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    out = np.zeros((matrices.shape[0], pos.shape[0], 3))
    for k in range(joints.shape[1]):
        m = matrices[:, joints[:, k]]  # (P, V, 4, 4)
        p = np.einsum("pvij,vj->pvi", m[..., :3, :3], pos) + m[..., :3, 3]
        out += w[None, :, k, None] * p
    return out
