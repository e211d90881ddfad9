"""A character's clips evaluated in float64, straight from the source keys, as glTF defines them.

The asset's own semantics, below every stage: the importer uses it to tell looping clips, the zombie
generator to place its pieces, and the float64 reference (crowd.anim.reference) builds on it.
- a clip is sampled at ``time = clip.start + phase * clip.duration``; looping clips wrap phase into
  [0, 1) in float64, one-shot clips clamp it to [0, 1];
- keys are interpolated as glTF says: LINEAR lerps translation/scale and slerps rotation, STEP holds,
  CUBICSPLINE is the Hermite spline of the spec (rotations renormalised);
- joints a clip does not animate keep their rest transform;
- morph weights interpolate linearly (STEP and CUBICSPLINE as for other paths), and targets a clip does
  not drive keep their default weight; a morphed vertex is its position plus the weighted deltas.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..transforms import quat_normalize, quat_slerp, trs_to_mat4
from .model import Channel, Clip, ModelError, Skeleton


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


def global_matrices(skeleton: Skeleton, local: LocalPose | np.ndarray) -> np.ndarray:
    """Model-space joint matrices (P, J, 4, 4), concatenated parents-first."""
    m = local.matrices() if isinstance(local, LocalPose) else np.asarray(local, dtype=np.float64)
    out = np.empty_like(m)
    for i, p in enumerate(skeleton.parents):
        out[:, i] = m[:, i] if p < 0 else out[:, p] @ m[:, i]
    return out


def sample_morph_weights(defaults: np.ndarray, clip: Clip, phases) -> np.ndarray:
    """Morph weights (P, M) of `clip` at each phase (P,): its weights channels' keys interpolated as glTF
    says (linearly: weights are not rotations), `defaults` (M,) for the targets no channel drives."""
    times = np.atleast_1d(phase_to_time(clip, phases))
    defaults = np.asarray(defaults, np.float64)
    out = np.broadcast_to(defaults, (times.shape[0], defaults.shape[0])).copy()
    for ch in clip.morph_channels:
        out[:, ch.morphs] = sample_channel(ch, times)
    return out


def morph_vertices(mesh, weights) -> tuple[np.ndarray, np.ndarray]:
    """A skinned mesh's bind-space positions and unit normals (float64) with the character's morph
    `weights` (M,) applied, as glTF defines it: position + sum of w * position delta over the mesh's
    targets, and likewise the normal (then normalised), before skinning."""
    positions = np.asarray(mesh.positions, np.float64).copy()
    normals = np.asarray(mesh.normals, np.float64).copy()
    if mesh.morph_count:
        w = np.asarray(weights, np.float64)[mesh.morph_targets]
        positions += np.einsum("t,tvc->vc", w, np.asarray(mesh.morph_positions, np.float64))
        normals += np.einsum("t,tvc->vc", w, np.asarray(mesh.morph_normals, np.float64))
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return positions, np.where(length > 1e-12, normals / np.maximum(length, 1e-12), normals)
