"""Accuracy: how far the animation pipeline's skinning matrices are from the float64 reference.

Contract:
- ``draw_samples(clips, rng, per_clip, blends)`` → ``Samples``: processor layers (float32, clip indices
  into `clips`) for single clips at random phases and for random blends of 2 to 4 layers;
- ``truth(skeleton, clips, samples)`` → float64 (P, J, 4, 4) skinning matrices straight from the
  source keys (crowd.anim.reference: no bake, no dual quaternions, no float32);
- ``shell_error(palette, truth, points)`` → (P, J, 6) metres: the error of virtual vertices;
- ``measure_gpu(ctx, skeleton, bake, layers, truth)``: the same for the GPU processor's palette.

The measure is ACL's (the Animation Compression Library): a vertex skinned rigidly to a joint at
``SHELL_M`` = 3 cm from it, along each of the joint's bind-pose axes, both ways. Rotation errors show
as 3 cm times the angle, translation errors in full, and both add up through the hierarchy, because
the matrices compared are the skinning matrices a vertex shader uses.

Phases and weights are drawn in float32 and the reference reads the same float32 values, so what is
measured is the pipeline's error, not the rounding of its inputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import reference
from ..asset.model import Clip, Skeleton
from .bake import AnimationBake
from ..frame import CLIP, MASK, MAX_LAYERS, PHASE, WEIGHT, empty_layers
from .processor import DEFAULT_INTERPOLATION, AnimationProcessor

SHELL_M = 0.03


@dataclass
class Samples:
    layers: np.ndarray  # float32 (P, MAX_LAYERS, 4): processor input, clip indices into the clip list
    single: np.ndarray  # bool (P,): one layer (per-clip errors are read from these)


def draw_samples(clips: list[Clip], rng: np.random.Generator, per_clip: int, blends: int) -> Samples:
    """`per_clip` random phases of every clip alone, then `blends` blends of 2 to 4 random clips at
    random phases with weights from 0.1 to 1 (unused layers have weight 0)."""
    c = len(clips)
    n = c * per_clip + blends
    layers = empty_layers(n, MAX_LAYERS)
    layers[: c * per_clip, 0, CLIP] = np.repeat(np.arange(c), per_clip)
    layers[: c * per_clip, 0, PHASE] = rng.uniform(0.0, 1.0, c * per_clip)
    layers[: c * per_clip, 0, WEIGHT] = 1.0
    b = slice(c * per_clip, n)
    counts = rng.integers(2, MAX_LAYERS + 1, blends)
    active = np.arange(MAX_LAYERS)[None, :] < counts[:, None]
    layers[b, :, CLIP] = rng.integers(0, c, (blends, MAX_LAYERS))
    layers[b, :, PHASE] = rng.uniform(0.0, 1.0, (blends, MAX_LAYERS))
    layers[b, :, WEIGHT] = np.where(active, rng.uniform(0.1, 1.0, (blends, MAX_LAYERS)), 0.0)
    single = np.zeros(n, bool)
    single[: c * per_clip] = True
    return Samples(layers, single)


def truth(skeleton: Skeleton, clips: list[Clip], layers: np.ndarray, masks=None) -> np.ndarray:
    """Float64 skinning matrices (P, J, 4, 4) of processor layers (P, L, 4) from the source clips, with
    the processor's joint masks (M, J) where a layer names one."""
    layers = np.asarray(layers, np.float32).astype(np.float64)
    n, lcount, _ = layers.shape
    poses = []
    for l in range(lcount):
        pose = reference.rest_pose(skeleton, n)
        clip_of = layers[:, l, CLIP].astype(np.int64)
        for c in np.unique(clip_of[layers[:, l, WEIGHT] > 0]):
            rows = np.flatnonzero((clip_of == c) & (layers[:, l, WEIGHT] > 0))
            sampled = reference.sample_clip(skeleton, clips[c], layers[rows, l, PHASE])
            pose.translation[rows], pose.rotation[rows], pose.scale[rows] = sampled.translation, sampled.rotation, sampled.scale
        poses.append(pose)
    weights = layers[:, :, WEIGHT].T
    if masks is None or np.all(layers[:, :, MASK] < 0):
        local = reference.blend(skeleton, poses, weights)
    else:  # the reference blends with one set of masks at a time: group the samples by the masks they use
        m = np.asarray(masks, np.float64)
        local = reference.rest_pose(skeleton, n)
        patterns, group = np.unique(layers[:, :, MASK].astype(np.int64), axis=0, return_inverse=True)
        for g, pattern in enumerate(patterns):
            rows = np.flatnonzero(group.ravel() == g)
            layer_masks = np.stack([m[k] if k >= 0 else np.ones(skeleton.joint_count) for k in pattern])
            part = reference.blend(skeleton, [reference.LocalPose(p.translation[rows], p.rotation[rows], p.scale[rows]) for p in poses],
                                   weights[:, rows], layer_masks)
            local.translation[rows], local.rotation[rows], local.scale[rows] = part.translation, part.rotation, part.scale
    return reference.skinning_matrices(skeleton, local)


def gpu_palette(ctx, bake: AnimationBake, layers: np.ndarray, interpolation: str = DEFAULT_INTERPOLATION, path: str = "auto",
                masks=None) -> np.ndarray:
    """(P, J, 3, 4) float32 palette of the GPU processor for `layers`, from a processor made for this
    one run and released after it."""
    proc = AnimationProcessor(ctx, bake, layers.shape[1], masks=masks, path=path, interpolation=interpolation)
    try:
        proc.resize(layers.shape[0])
        proc.process(layers)
        return proc.read_palette()
    finally:
        proc.release()


def measure_gpu(ctx, skeleton: Skeleton, bake: AnimationBake, layers: np.ndarray, truth_matrices: np.ndarray,
                interpolation: str = DEFAULT_INTERPOLATION, path: str = "auto", masks=None) -> np.ndarray:
    """(P, J, 6) shell errors of the GPU processor's palette for `layers`, against the float64 truth."""
    return shell_error(gpu_palette(ctx, bake, layers, interpolation, path, masks), truth_matrices, shell_points(skeleton))


def shell_points(skeleton: Skeleton, radius: float = SHELL_M) -> np.ndarray:
    """(J, 6, 4) homogeneous bind-space points: each joint's position ± radius along its bind axes."""
    bind = np.linalg.inv(skeleton.inverse_bind)  # (J, 4, 4) joint → model space at bind time
    axes = bind[:, :3, :3] / np.linalg.norm(bind[:, :3, :3], axis=1, keepdims=True)  # unit columns
    offsets = np.concatenate([axes, -axes], axis=2).transpose(0, 2, 1) * radius  # (J, 6, 3)
    points = np.ones((skeleton.joint_count, 6, 4))
    points[..., :3] = bind[:, None, :3, 3] + offsets
    return points


def shell_error(palette: np.ndarray, truth_matrices: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P, J, 6) metres between the shell points skinned by `palette` ((P, J, 3, 4) rows, any float)
    and by the float64 truth ((P, J, 3|4, 4))."""
    delta = np.asarray(palette, np.float64)[..., :3, :] - np.asarray(truth_matrices, np.float64)[..., :3, :]
    return np.linalg.norm(np.einsum("pjrc,jkc->pjkr", delta, points), axis=-1)


def summarise(errors_m: np.ndarray) -> dict:
    """max, 99th percentile (mm) and share of virtual vertices under 1 mm."""
    e = np.asarray(errors_m, np.float64).ravel()
    if e.size == 0:
        return {"max_error_mm": 0.0, "p99_error_mm": 0.0, "share_under_1mm": 1.0}
    return {"max_error_mm": float(e.max() * 1e3), "p99_error_mm": float(np.percentile(e, 99) * 1e3),
            "share_under_1mm": float(np.count_nonzero(e < 1e-3) / e.size)}
