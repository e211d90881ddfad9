"""Accuracy: how far the animation pipeline's skinning matrices are from the float64 reference.

Contract:
- ``draw_samples(clips, rng, per_clip, blends)`` → ``Samples``: processor layers (float32, clip indices
  into `clips`) for single clips at random phases and for random blends of 2 to 4 layers;
- ``truth(skeleton, clips, samples)`` → float64 (P, J, 4, 4) skinning matrices straight from the
  source keys (crowd.anim.reference: no bake, no dual quaternions, no float32);
- ``shell_error(palette, truth, points)`` → (P, J, 6) metres: the error of virtual vertices;
- ``measure_gpu(ctx, skeleton, bake, layers, truth)``: the same for the GPU processor's palette;
- ``ClipMaxima(skeleton, clips).find(palette_of)`` → one ``ClipMaximum`` per clip: the largest error
  of the clip alone over all phases, with its phase and joint, found by refinement rather than read off
  samples (random phases missed the attack's 0.485 mm at hand_r_socket and reported 0.39 mm).

The measure is ACL's (the Animation Compression Library): a vertex skinned rigidly to a joint at
``SHELL_M`` = 3 cm from it, along each of the joint's bind-pose axes, both ways. Rotation errors show
as 3 cm times the angle, translation errors in full, and both add up through the hierarchy, because
the matrices compared are the skinning matrices a vertex shader uses.

Phases and weights are drawn in float32 and the reference reads the same float32 values, so what is
measured is the pipeline's error, not the rounding of its inputs.
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from . import reference
from ..asset.model import Clip, Skeleton
from .bake import AnimationBake
from ..frame import CLIP, MASK, MAX_LAYERS, PHASE, WEIGHT, empty_layers
from .processor import AnimationProcessor
from .processor_inputs import DEFAULT_INTERPOLATION
from .shell import SHELL_M, shell_error, shell_points  # noqa: F401  (part of this module's contract)

# The maximum search over one clip's phase (ClipMaxima). Seeds: 240 per second of clip, 8 between two
# 30 fps keys, and at least SEEDS_PER_KEY between two of the clip's own keys (so a clip keyed at 120 fps
# gets 4 too), at most MAX_SEEDS a clip; nlerp against slerp peaks twice between two keys (near a
# fifth and four fifths of the way), and a 60 fps bake still gets 4 seeds per interval, so every hump
# of the error is seen. Then the
# CANDIDATES highest local maxima of each clip are refined on a grid of REFINE_GRID phases between
# their neighbours, the bracket shrinking 8.5 times a round, until no clip's maximum grows by more than
# REFINE_TOLERANCE in a round. Near a smooth peak the gain falls with the square of the bracket, so two
# or three rounds do.
SEED_RATE = 240.0
SEEDS_PER_KEY = 4
MAX_SEEDS = 16384
CANDIDATES = 4
REFINE_GRID = 16
REFINE_TOLERANCE = 0.01
MAX_ROUNDS = 12


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


@contextmanager
def gpu_palettes(ctx, bake: AnimationBake, layer_count: int, interpolation: str = DEFAULT_INTERPOLATION, path: str = "auto", masks=None):
    """A function layers → (P, J, 3, 4) float32 palette of one GPU processor, kept for several runs (a
    search runs a few rounds: one shader compile, not one a round), released on exit."""
    proc = AnimationProcessor(ctx, bake, layer_count, masks=masks, path=path, interpolation=interpolation)

    def palette_of(layers: np.ndarray) -> np.ndarray:
        proc.resize(layers.shape[0])
        proc.process(layers)
        return proc.read_palette()

    try:
        yield palette_of
    finally:
        proc.release()


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


def summarise(errors_m: np.ndarray) -> dict:
    """max, 99th percentile (mm) and shares of virtual vertices under 1 mm and under 0.1 mm (ACL's bar)."""
    e = np.asarray(errors_m, np.float64).ravel()
    if e.size == 0:
        return {"max_error_mm": 0.0, "p99_error_mm": 0.0, "share_under_1mm": 1.0, "share_under_0_1mm": 1.0}
    return {"max_error_mm": float(e.max() * 1e3), "p99_error_mm": float(np.percentile(e, 99) * 1e3),
            "share_under_1mm": float(np.count_nonzero(e < 1e-3) / e.size), "share_under_0_1mm": float(np.count_nonzero(e < 1e-4) / e.size)}


def _key_intervals(clip: Clip) -> int:
    """Key intervals of the clip's most densely keyed channel."""
    return max((int(c.times.shape[0]) - 1 for c in clip.channels), default=1)


def single_clip_layers(clip_of, phases) -> np.ndarray:
    """(P, 1, 4) float32 layers: clip `clip_of[p]` alone at phase `phases[p]`, weight 1."""
    clip_of = np.asarray(clip_of)
    layers = empty_layers(len(clip_of), 1)
    layers[:, 0, CLIP] = clip_of
    layers[:, 0, PHASE] = phases
    layers[:, 0, WEIGHT] = 1.0
    return layers


@dataclass(frozen=True)
class ClipMaximum:
    clip: int  # index into the clips
    phase: float  # the float32 phase the maximum was measured at (what the processor and the truth read)
    joint: int
    error_m: float  # the shell error there (max over the joint's 6 shell points)
    rounds: int  # refinement rounds until it changed by less than the tolerance
    poses: int  # poses evaluated for this clip, seeds included


class ClipMaxima:
    """The largest shell error of each clip alone over its whole phase range, with its phase and joint.

    The seeds and their float64 truth depend only on the clips, so they are made once and serve every
    configuration (bake rate, storage, interpolation) a report measures; ``find`` then takes the
    configuration as a function from layers to its palette."""

    def __init__(self, skeleton: Skeleton, clips: list[Clip], seed_rate: float = SEED_RATE):
        self.skeleton = skeleton
        self.clips = list(clips)
        self.points = shell_points(skeleton)
        counts = [min(MAX_SEEDS, max(3, int(math.ceil(c.duration * seed_rate)) + 1, SEEDS_PER_KEY * _key_intervals(c) + 1)) for c in self.clips]
        self.seed_clip = np.repeat(np.arange(len(self.clips)), counts)
        self.seed_layers = single_clip_layers(self.seed_clip, np.concatenate([np.linspace(0.0, 1.0, n) for n in counts]))
        self.seed_truth = truth(skeleton, self.clips, self.seed_layers)

    def _errors(self, palette_of, layers: np.ndarray, truth_matrices: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Per pose: the largest shell error (metres) and the joint it is at."""
        if truth_matrices is None:
            truth_matrices = truth(self.skeleton, self.clips, layers)
        e = shell_error(palette_of(layers), truth_matrices, self.points).max(axis=2)  # (P, J)
        joint = np.argmax(e, axis=1)
        return e[np.arange(len(e)), joint], joint

    def find(self, palette_of, tolerance: float = REFINE_TOLERANCE, candidates: int = CANDIDATES, grid: int = REFINE_GRID,
             max_rounds: int = MAX_ROUNDS) -> list[ClipMaximum]:
        """One ClipMaximum per clip. `palette_of(layers)` → (P, J, 3, 4) palette rows of (P, 1, 4) layers."""
        seed_error, seed_joint = self._errors(palette_of, self.seed_layers, self.seed_truth)
        seed_phase = self.seed_layers[:, 0, PHASE].astype(np.float64)
        count = len(self.clips)
        brackets: list[_Bracket] = []
        for c in range(count):
            rows = np.flatnonzero(self.seed_clip == c)
            e = seed_error[rows]
            peaks = np.flatnonzero((e >= np.concatenate([[-np.inf], e[:-1]])) & (e >= np.concatenate([e[1:], [-np.inf]])))
            for i in peaks[np.argsort(-e[peaks], kind="stable")][:candidates]:
                brackets.append(_Bracket(c, seed_phase[rows[max(i - 1, 0)]], seed_phase[rows[min(i + 1, len(rows) - 1)]],
                                         seed_phase[rows[i]], float(e[i]), int(seed_joint[rows[i]])))
        poses = np.bincount(self.seed_clip, minlength=count).astype(np.int64)
        rounds = np.zeros(count, np.int64)
        done = np.zeros(count, bool)

        def best(c) -> _Bracket:
            return max((b for b in brackets if b.clip == c), key=lambda b: b.error)

        for _ in range(max_rounds):
            active = [b for b in brackets if not done[b.clip]]
            if not active:
                break
            before = {b.clip: best(b.clip).error for b in active}
            layers = single_clip_layers(np.repeat([b.clip for b in active], grid),
                                        np.concatenate([np.linspace(b.low, b.high, grid + 2)[1:-1] for b in active]))
            error, joint = self._errors(palette_of, layers)
            used = layers[:, 0, PHASE].astype(np.float64)  # the float32 phases the processor and the truth read
            for k, b in enumerate(active):
                i = k * grid + int(np.argmax(error[k * grid : (k + 1) * grid]))
                if error[i] > b.error:
                    b.phase, b.error, b.joint = float(used[i]), float(error[i]), int(joint[i])
                step = (b.high - b.low) / (grid + 1)
                b.low, b.high = max(b.phase - step, 0.0), min(b.phase + step, 1.0)
                poses[b.clip] += grid
            for c, old in before.items():
                rounds[c] += 1
                new = best(c).error
                narrow = all(b.high - b.low < 1e-7 for b in brackets if b.clip == c)  # float32 phases go no finer
                done[c] = new - old <= tolerance * new or narrow
        out = []
        for c in range(count):
            b = best(c) if any(b.clip == c for b in brackets) else _Bracket(c, 0.0, 0.0, 0.0, 0.0, 0)
            out.append(ClipMaximum(c, b.phase, b.joint, b.error, int(rounds[c]), int(poses[c])))
        return out


@dataclass
class _Bracket:
    """A phase interval of one clip that holds a local maximum, and the best pose found in it so far."""

    clip: int
    low: float
    high: float
    phase: float
    error: float
    joint: int
