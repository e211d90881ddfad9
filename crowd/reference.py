"""The float64 reference: exact joint and skinning matrices straight from the source keys.

No baking, no dual quaternions, no float32: every later numeric claim (the bake's error, the GPU
processor's error, the weapon's error) is measured against this module.

Definitions (shared with the processor, so the two can be compared):
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

from dataclasses import dataclass

import numpy as np

from .model import Channel, Clip, ModelError, Skeleton
from .transforms import quat_normalize, quat_slerp, trs_to_mat4

REST_THRESHOLD = 1e-6


@dataclass
class LocalPose:
    """Local joint transforms for a batch of P poses."""

    translation: np.ndarray  # (P, J, 3)
    rotation: np.ndarray  # (P, J, 4)
    scale: np.ndarray  # (P, J, 3)

    def matrices(self) -> np.ndarray:
        return trs_to_mat4(self.translation, self.rotation, self.scale)


def rest_pose(skeleton: Skeleton, count: int = 1) -> LocalPose:
    return LocalPose(
        np.broadcast_to(skeleton.rest_translation, (count,) + skeleton.rest_translation.shape).copy(),
        np.broadcast_to(skeleton.rest_rotation, (count,) + skeleton.rest_rotation.shape).copy(),
        np.broadcast_to(skeleton.rest_scale, (count,) + skeleton.rest_scale.shape).copy(),
    )


def phase_to_time(clip: Clip, phase) -> np.ndarray:
    phase = np.asarray(phase, dtype=np.float64)
    if not np.all(np.isfinite(phase)):
        raise ModelError(f"clip {clip.name!r}: phase holds NaN or Inf")
    phase = np.mod(phase, 1.0) if clip.loop else np.clip(phase, 0.0, 1.0)
    return clip.start + phase * clip.duration


def sample_channel(channel: Channel, times: np.ndarray) -> np.ndarray:
    """Values of one channel at the given times (float64), glTF semantics, clamped outside the keys."""
    times = np.asarray(times, dtype=np.float64)
    kt = channel.times
    values = channel.values
    cubic = channel.interpolation == "CUBICSPLINE"
    keys = values[:, 1, :] if cubic else values
    if kt.shape[0] == 1:
        return np.broadcast_to(keys[0], times.shape + keys.shape[1:]).copy()
    tc = np.clip(times, kt[0], kt[-1])
    i0 = np.clip(np.searchsorted(kt, tc, side="right") - 1, 0, kt.shape[0] - 2)
    i1 = i0 + 1
    span = kt[i1] - kt[i0]
    u = (tc - kt[i0]) / span
    if channel.interpolation == "STEP":
        # STEP holds key k until key k+1; at and after the last key the last value holds.
        out = np.where((tc >= kt[-1])[..., None], keys[-1], keys[i0])
    elif channel.interpolation == "LINEAR":
        if channel.path == "rotation":
            out = quat_slerp(keys[i0], keys[i1], u)
        else:
            out = keys[i0] + (keys[i1] - keys[i0]) * u[..., None]
    else:
        u2, u3 = u * u, u * u * u
        h00 = 2 * u3 - 3 * u2 + 1
        h10 = u3 - 2 * u2 + u
        h01 = -2 * u3 + 3 * u2
        h11 = u3 - u2
        out_tangent = values[i0, 2, :]
        in_tangent = values[i1, 0, :]
        s = span[..., None]
        out = h00[..., None] * keys[i0] + h10[..., None] * s * out_tangent + h01[..., None] * keys[i1] + h11[..., None] * s * in_tangent
    if channel.path == "rotation":
        out = quat_normalize(out)
    return out


def sample_clip(skeleton: Skeleton, clip: Clip, phases) -> LocalPose:
    """Local pose of `clip` at each phase (P,), straight from the source keys."""
    times = np.atleast_1d(phase_to_time(clip, phases))
    pose = rest_pose(skeleton, times.shape[0])
    for ch in clip.channels:
        getattr(pose, ch.path)[:, ch.joint] = sample_channel(ch, times)
    return pose


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


def global_matrices(skeleton: Skeleton, local: LocalPose | np.ndarray) -> np.ndarray:
    """Model-space joint matrices (P, J, 4, 4), concatenated parents-first."""
    m = local.matrices() if isinstance(local, LocalPose) else np.asarray(local, dtype=np.float64)
    out = np.empty_like(m)
    for i, p in enumerate(skeleton.parents):
        out[:, i] = m[:, i] if p < 0 else out[:, p] @ m[:, i]
    return out


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
