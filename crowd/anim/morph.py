"""Morph weights: a character's weight tracks baked beside its joint tracks, and each agent's weights.

Contract (issue 23, points 2 and 4): ``bake_morphs(character, clips, joint_bake, variation, seed)`` →
``MorphBake`` or None where the scene needs no morph weights (the character has no targets, or no baked
clip drives one, every default weight is 0 and no variation is asked): then nothing is allocated and the
processor and the draw run without morph code.

Layout of ``tracks`` (rows, M) float32, M the character's morph targets:
- row 0 holds the default weights (glTF's mesh and node weights): what a clip without weight channels
  plays;
- each baked clip with weight channels owns as many rows as its joint frames, sampled at the same
  phases (closing frame included), so a layer's row and lerp factor are the joints' (``frame_position``);
  a clip without them plays row 0 (``clip_rows`` (first row, frames): (0, 1)).

An agent's weights, per target m, as the processor computes them (``reference_weights`` is the float64
model):
- the layers' weights blend the clips' tracks: sum of max(w_l, 0) * track_l(m) over S = the sum of
  max(w_l, 0) (the same weights as the joints; joint masks do not apply: a target is no joint); where S
  is 0, the defaults;
- plus the agent's variation, fixed for the agent: lo + (hi - lo) * u, u a hash of (seed, character,
  the agent's number among its character's) in [0, 1), for each target given a range;
- clamped to ±MAX_MORPH_WEIGHT;
- where the panel holds a target's weight (for one agent or all of the character's), that weight.
The draw fetches only targets whose weight is at least ACTIVE_WEIGHT in size, at most MORPH_PAIRS of
them an agent (the largest first, ties by target): the processor writes them as (target, weight) pairs
into the texel before the agent's joint 0 in its palette row (across the three planes), a weight of 0
ending the list.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import CrowdError
from ..asset.model import Character, ModelError
from ..asset.pose import sample_morph_weights
from ..frame import CLIP, PHASE, WEIGHT

MAX_MORPH_WEIGHT = 10.0  # as the importer's bound (crowd.asset.gltf.reader.MAX_MORPH_WEIGHT)
# Below this in size a target's weight is not drawn: at most 1/1024 of its largest delta (0.05 mm of a
# 5 cm jaw), where fetching it would cost as much as a weight of 1.
ACTIVE_WEIGHT = 1.0 / 1024.0
# Targets drawn per agent at most: the (target, weight) pairs one palette texel holds across its three
# RGBA32F planes. One texel keeps the draw's reading simple (the texel before joint 0, whatever the
# character); a crowd's zombies move a few targets each (a face in close-up may move more: its smaller
# weights are then left out, the largest kept).
MORPH_PAIRS = 6
ERROR_WARN = 0.01  # a baked weight this far from the source's says so in the bake's warnings (1 % of a full shape)
ALL_HELD, NOT_HELD = -1, -2  # held weights for every agent of a character, or for none (else one agent's number)


class MorphError(CrowdError, ValueError):
    """Bad morph input; the message is one line."""


@dataclass
class MorphBake:
    names: tuple[str, ...]  # the character's morph targets (M)
    tracks: np.ndarray  # float32 (rows, M): row 0 the defaults, then the clips' frames
    clip_rows: np.ndarray  # int32 (C, 2): per baked clip, its first row and frame count ((0, 1): the defaults)
    variation: np.ndarray  # float32 (M, 2): per target the (lo, hi) range of the agents' offsets (0, 0: none)
    seed: int  # the variation's
    error: tuple = (0.0, "", "", 0.0)  # track_error: (weight, clip, target, phase) of the largest bake error

    @property
    def count(self) -> int:
        return len(self.names)

    @property
    def nbytes(self) -> int:
        return int(self.tracks.nbytes + self.clip_rows.nbytes + self.variation.nbytes)


def check_variation(character: Character, variation: dict | None) -> np.ndarray:
    """{target name: (lo, hi)} → float32 (M, 2), each within [0, 1] and lo <= hi, or MorphError."""
    out = np.zeros((len(character.morphs), 2), np.float32)
    for name, value in (variation or {}).items():
        if name not in character.morphs:
            raise MorphError(f"character {character.name!r} has no morph target {name!r}; it has {', '.join(character.morphs) or 'none'}")
        try:
            lo, hi = (float(v) for v in value)
        except (TypeError, ValueError):
            raise MorphError(f"morph variation of {name!r} must be two numbers (lo, hi), got {value!r}") from None
        if not (0.0 <= lo <= hi <= 1.0):  # NaN fails this too
            raise MorphError(f"morph variation of {name!r} must be 0 <= lo <= hi <= 1, got ({lo}, {hi})")
        out[character.morphs.index(name)] = lo, hi
    return out


def bake_morphs(character: Character, clips, joint_bake, variation: dict | None = None, seed: int = 0) -> MorphBake | None:
    """The morph tracks of `clips` (the Clip objects `joint_bake` baked, in its order) and the scene's
    `variation` ({target: (lo, hi)}); None where none of it moves a target."""
    if not character.morphs:
        if variation:
            raise MorphError(f"character {character.name!r} has no morph targets; a morph variation cannot apply")
        return None
    ranges = check_variation(character, variation)
    clips = list(clips)
    if [c.name for c in clips] != [c.name for c in joint_bake.clips]:
        raise MorphError("the morph bake needs the clips of the joint bake, in its order")
    defaults = np.asarray(character.morph_defaults, np.float64)
    driven = any(c.morph_channels for c in clips)
    if not driven and not np.any(defaults) and not np.any(ranges[:, 1]):
        return None
    rows = [defaults[None]]
    clip_rows = np.zeros((len(clips), 2), np.int32)
    clip_rows[:, 1] = 1
    first = 1
    for k, (clip, info) in enumerate(zip(clips, joint_bake.clips)):
        if not clip.morph_channels:
            continue
        try:
            clip.validate(character.skeleton, len(character.morphs))
        except ModelError as exc:
            raise MorphError(str(exc)) from None
        n = info.frame_count - 1
        phases = np.arange(n + 1, dtype=np.float64) / n
        if clip.loop:
            phases[-1] = 0.0  # the closing frame repeats the first, as the joints' does
        rows.append(sample_morph_weights(defaults, clip, phases))
        clip_rows[k] = first, n + 1
        first += n + 1
    tracks = np.concatenate(rows)
    if not np.all(np.isfinite(tracks)):
        raise MorphError("baked morph weights hold NaN or Inf")
    out = MorphBake(tuple(character.morphs), np.clip(tracks, -MAX_MORPH_WEIGHT, MAX_MORPH_WEIGHT).astype(np.float32), clip_rows,
                    ranges, int(seed) & 0xFFFFFFFF)
    out.error = track_error(out, character, clips, joint_bake)
    if out.error[0] > ERROR_WARN:
        error, clip, target, phase = out.error
        joint_bake.warnings.append(f"morph weights baked at {joint_bake.fps} fps are off by up to {error:.3g} (clip {clip!r}, target "
                                   f"{target!r}, phase {phase:.3f}), more than {ERROR_WARN:g}: bake at a higher rate, or at the source's")
    return out


def pcg_hash(values) -> np.ndarray:
    """PCG's output permutation of uint32 values (as shaders/processor_common.glsl's pcg_hash)."""
    with np.errstate(over="ignore"):
        state = np.asarray(values, np.uint32) * np.uint32(747796405) + np.uint32(2891336453)
        word = ((state >> ((state >> np.uint32(28)) + np.uint32(4))) ^ state) * np.uint32(277803737)
    return (word >> np.uint32(22)) ^ word


def variation_offsets(bake: MorphBake, character_index: int, agents) -> np.ndarray:
    """(N, M) float64 offsets of agents numbered `agents` among their character's (`character_index`
    in the cast): lo + (hi - lo) * u, u in [0, 1) from a hash exact in float32 (24 bits)."""
    agents = np.asarray(agents, np.int64).astype(np.uint32)
    m = np.arange(bake.count, dtype=np.uint32)
    key = pcg_hash(np.uint32(bake.seed) ^ pcg_hash(np.uint32(character_index) * np.uint32(0x9E3779B9) + agents[:, None] * np.uint32(bake.count) + m))
    u = (key >> np.uint32(8)).astype(np.float64) / float(1 << 24)
    lo, hi = bake.variation[:, 0].astype(np.float64), bake.variation[:, 1].astype(np.float64)
    return np.where(hi > lo, lo + (hi - lo) * u, lo)


def reference_weights(bake: MorphBake, joint_bake, layers, character_index: int = 0, agents=None, held=None, held_agent: int = NOT_HELD) -> np.ndarray:
    """Float64 model of the processor's morph weights: (N, M) for `layers` (N, L, 4) of agents numbered
    `agents` (default 0 .. N - 1) among their character's; `held` (M,) the held weights (< 0: not held)
    of agent `held_agent` (ALL_HELD: every agent; NOT_HELD: none)."""
    layers = np.asarray(layers, np.float64)
    n = layers.shape[0]
    agents = np.arange(n) if agents is None else np.asarray(agents, np.int64)
    tracks = bake.tracks.astype(np.float64)
    weight = np.maximum(layers[:, :, WEIGHT], 0.0)  # (N, L)
    total = weight.sum(axis=1)
    out = np.zeros((n, bake.count))
    for l in range(layers.shape[1]):
        clip = layers[:, l, CLIP].astype(np.int64)
        info = joint_bake.clip_table.astype(np.float64)[clip]
        first, count = bake.clip_rows[clip, 0].astype(np.int64), bake.clip_rows[clip, 1].astype(np.int64)
        phase = layers[:, l, PHASE]
        looping = info[:, 3] > 0.5
        phase = np.where(looping, phase - np.floor(phase), np.clip(phase, 0.0, 1.0))
        f = phase * np.maximum(count - 1.0, 0.0)
        i0 = np.clip(np.floor(f), 0.0, np.maximum(count - 2.0, 0.0)).astype(np.int64)
        u = (f - i0)[:, None]
        i1 = np.minimum(i0 + 1, count - 1)
        sampled = tracks[first + i0] + (tracks[first + i1] - tracks[first + i0]) * u
        out += weight[:, l, None] * sampled
    blended = np.where(total[:, None] > 0.0, out / np.where(total > 0.0, total, 1.0)[:, None], tracks[0][None])
    weights = np.clip(blended + variation_offsets(bake, character_index, agents), -MAX_MORPH_WEIGHT, MAX_MORPH_WEIGHT)
    if held is not None and held_agent != NOT_HELD:
        rows = np.ones(n, bool) if held_agent == ALL_HELD else agents == held_agent
        held = np.asarray(held, np.float64)
        weights[np.ix_(rows, held >= 0.0)] = held[held >= 0.0]
    return weights


def active_pairs(weights, limit: int = MORPH_PAIRS) -> np.ndarray:
    """(N, limit, 2) float64 (target, weight) pairs the draw fetches, per agent: the targets whose weight
    is at least ACTIVE_WEIGHT in size, the largest first (ties by target), then (0, 0)s."""
    w = np.asarray(weights, np.float64)
    n, m = w.shape
    size = np.where(np.abs(w) >= ACTIVE_WEIGHT, np.abs(w), -1.0)
    order = np.lexsort((np.broadcast_to(np.arange(m), (n, m)), -size), axis=1)[:, :limit]
    chosen = np.take_along_axis(size, order, axis=1) >= 0.0
    out = np.zeros((n, limit, 2))
    out[..., 0] = np.where(chosen, order, 0)
    out[..., 1] = np.where(chosen, np.take_along_axis(w, order, axis=1), 0.0)
    return out


def track_error(bake: MorphBake, character: Character, clips, joint_bake, per_interval: int = 8) -> tuple[float, str, str, float]:
    """(error, clip, target, phase): the largest difference between a baked weight track, lerped between
    its frames as the processor does, and the clip's weights from the source keys (crowd.asset.pose), over
    every clip with weight channels and every target it drives. Found by search: `per_interval` samples
    in each frame interval, then a golden-section refinement around the worst of them (the difference is
    smooth between the source's keys; a key inside an interval bends it, which the samples catch)."""
    defaults = np.asarray(character.morph_defaults, np.float64)
    worst = (0.0, "", "", 0.0)
    for clip, info, (first, frames) in zip(clips, joint_bake.clips, bake.clip_rows):
        if not clip.morph_channels or frames < 2:
            continue
        track = bake.tracks[first:first + frames].astype(np.float64)

        def error(phase, target):
            phase = np.atleast_1d(np.asarray(phase, np.float64))
            f = phase * (frames - 1)
            i0 = np.clip(np.floor(f), 0, frames - 2).astype(np.int64)
            baked = track[i0, target] + (track[i0 + 1, target] - track[i0, target]) * (f - i0)
            exact = sample_morph_weights(defaults, clip, np.where(phase >= 1.0, 1.0 - 1e-12, phase) if clip.loop else phase)[:, target]
            return np.abs(baked - exact)

        phases = np.linspace(0.0, 1.0, (frames - 1) * per_interval + 1)
        for target in sorted({int(m) for ch in clip.morph_channels for m in ch.morphs}):
            e = error(phases, target)
            k = int(np.argmax(e))
            lo, hi = phases[max(k - 1, 0)], phases[min(k + 1, len(phases) - 1)]
            best_p, best_e = float(phases[k]), float(e[k])
            ratio = (math.sqrt(5.0) - 1.0) / 2.0
            for _ in range(40):  # golden section on the bracket around the worst sample
                a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
                ea, eb = float(error(a, target)[0]), float(error(b, target)[0])
                if ea > eb:
                    hi = b
                else:
                    lo = a
                for p_, e_ in ((a, ea), (b, eb)):
                    if e_ > best_e:
                        best_p, best_e = float(p_), e_
            if best_e > worst[0]:
                worst = (best_e, clip.name, bake.names[target], best_p)
    return worst
