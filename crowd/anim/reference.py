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
  times its joint mask; rotations are sign-aligned to the heaviest layer and normalised after a
  weighted sum; translations and scales are weighted means; a joint whose total weight is below
  ``REST_THRESHOLD`` takes its rest transform.
"""

from __future__ import annotations

import numpy as np

from ..asset.model import ModelError, Skeleton
from ..asset.pose import LocalPose, global_matrices, phase_to_time, rest_pose, sample_channel, sample_clip
from ..transforms import quat_normalize

__all__ = ["REST_THRESHOLD", "LocalPose", "blend", "global_matrices", "phase_to_time", "pose", "rest_pose", "sample_channel",
           "sample_clip", "skin_points", "skinning_matrices"]

REST_THRESHOLD = 1e-6


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
    w = np.maximum(w, 0.0)[:, :, None]  # (L, P, 1)
    if masks is not None:
        m = np.clip(np.asarray(masks, dtype=np.float64).reshape(len(poses), 1, j), 0.0, 1.0)
        w = w * m  # (L, P, J)
    else:
        w = np.broadcast_to(w, (len(poses), count, j))
    total = w.sum(axis=0)  # (P, J)
    q = np.stack([p.rotation for p in poses])  # (L, P, J, 4)
    heaviest = np.argmax(w, axis=0)  # (P, J)
    ref = np.take_along_axis(q, heaviest[None, :, :, None], axis=0)[0]
    sign = np.where(np.sum(q * ref[None], axis=-1) < 0.0, -1.0, 1.0)
    safe_total = np.where(total < REST_THRESHOLD, 1.0, total)
    rot = quat_normalize(np.sum((w * sign)[..., None] * q, axis=0))
    tr = np.sum(w[..., None] * np.stack([p.translation for p in poses]), axis=0) / safe_total[..., None]
    sc = np.sum(w[..., None] * np.stack([p.scale for p in poses]), axis=0) / safe_total[..., None]
    rest = rest_pose(skeleton, count)
    low = (total < REST_THRESHOLD)[..., None]
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
