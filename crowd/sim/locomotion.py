"""How the AI animates locomotion: idle, walk and run weighted by ground speed on one phase that
advances by speed over the blended stride (so feet do not slide), the wrapped float64 phase itself, and
the turn about the planted foot."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..frame import CLIP, PHASE, WEIGHT, empty_layers
from .config import LAYERS
from .motion import FOOT_SAMPLES, Motion


def locomotion_weights(m: Motion, speed: np.ndarray, walk: np.ndarray, speed_factor: np.ndarray, out=None):
    """(idle, walk, run weights, run share of the stride) from ground speed, for agents whose walk
    speeds are `walk` and run speeds `m.run_speed * speed_factor`:
    - from the walk's slowest playback (``m.walk_slowest`` of `walk`) up to `walk` the walk plays alone,
      slowed down (phase_rate), so its planted feet keep pace with the ground;
    - below that it blends with idle, at the slowest playback;
    - from `walk` to the run speed the walk blends into the run, one phase for both.
    `out`: three arrays (a layer's strided weight column, say) the weights are written into by the
    operations that make them, rounded once, instead of new arrays."""
    to_walk = np.minimum(speed / (m.walk_slowest * walk), 1.0)
    run_t = np.minimum(np.maximum((speed - walk) / (m.run_speed * speed_factor - walk), 0.0), 1.0)
    out = out or (None, None, None)
    return (np.subtract(1.0, to_walk, out=out[0], casting="unsafe"), np.multiply(to_walk, 1.0 - run_t, out=out[1], casting="unsafe"),
            np.multiply(to_walk, run_t, out=out[2], casting="unsafe"), run_t)


def blended_stride(m: Motion, run_t, scale=1.0):
    """Metres a cycle of the walk-run blend at run share `run_t`, for agents of size `scale`."""
    return (m.walk_stride + run_t * (m.run_stride - m.walk_stride)) * scale


def phase_rate(m: Motion, speed, walk, run_t, scale=1.0):
    """Cycles a second of the shared locomotion phase, for agents at `speed` whose walk speeds are
    `walk` and whose run shares are `run_t` (locomotion_weights): speed over the blended stride, so that
    a planted foot keeps pace with the ground. Below the walk's slowest playback the walk's weight
    falls instead of its rate, so the rate stays there: its planted foot, at that weight, still moves
    with the ground (idle's feet stand still). Standing agents play idle at its own rate. `scale`: the
    agents' sizes, which their strides grow with (the skinning shader scales the whole model)."""
    moving = np.maximum(speed, m.walk_slowest * walk) / blended_stride(m, run_t, scale)
    return np.where(speed > 0.0, moving, 1.0 / np.maximum(m.duration["idle"], 1e-3))


def locomotion_layers(m: Motion, speed: float, frames: int, dt: float, speed_factor: float = 1.0):
    """One agent walking straight at a steady `speed` (m/s) for `frames` frames `dt` apart, as the AI
    animates it (crowd.anim.foot_skate measures what its feet do): its (frames, 4, 4) float32 layers
    and the distance (frames,) float64 it has covered at each frame."""
    walk = np.array([m.walk_speed * speed_factor])
    speeds = np.array([float(speed)])
    w = locomotion_weights(m, speeds, walk, np.array([speed_factor]))
    rate = float(phase_rate(m, speeds, walk, w[3])[0])
    t = np.arange(frames) * dt
    layers = empty_layers(frames, LAYERS)
    for layer, role in enumerate(("idle", "walk", "run")):
        layers[:, layer, CLIP] = m.clip[role]
        layers[:, layer, PHASE] = np.mod(rate * t, 1.0)
        layers[:, layer, WEIGHT] = float(w[layer][0])
    return layers, speed * t


def advance_phase(phase: np.ndarray, step, where=True) -> np.ndarray:
    """Advance float64 clip phases in place by `step` (cycles) and wrap them into [0, 1); `where`: only
    those phases (the others are left unwritten: another process may own them).

    Why phases and not a clock: a float32 clock of seconds has a 2 ms step after 10 hours (16 ms
    after 3 days), so phase = time / duration would jitter by whole key intervals; a wrapped float64
    phase keeps its 1e-16 resolution forever (crowd-bench error's "10 hours" case measures both)."""
    np.add(phase, step, out=phase, where=where)
    np.subtract(phase, np.floor(phase), out=phase, where=where)
    return phase


def turn_about_planted_foot(m: Motion, phase, weights, hx0, hz0, hx1, hz1, scale) -> tuple[np.ndarray, np.ndarray]:
    """The ground shift (dx, dz) that turns agents from heading (hx0, hz0) to (hx1, hz1) about the foot
    they stand on instead of about their origin, as a walker pivots on its stance foot: that foot stays
    where it is in world space. Each locomotion clip's pivot at a phase is the middle of its foot joints
    within the contact height (above each one's own lowest point): one foot's heel and toe, or both
    feet's (Motion.pivots); the agent's is the mean of its clips' pivots, weighted by their layer weights
    (`weights`: idle, walk, run) among the clips with a foot down, if those weigh half or more; else (a
    run's flight) no shift. A planted foot still turns with the body (a foot lock would twist the leg
    instead), so its joints slide by their distance from the pivot times the turn."""
    n = np.shape(phase)[0]
    if m.pivots is None or n == 0:
        return np.zeros(n), np.zeros(n)
    f = np.asarray(phase, np.float64) * FOOT_SAMPLES
    i = np.minimum(np.maximum(np.floor(f), 0), FOOT_SAMPLES - 1).astype(np.int64)
    u = f - i
    mx, mz, down = np.zeros(n), np.zeros(n), np.zeros(n)
    for r, w in enumerate(weights):
        if not np.any(w):
            continue  # a clip nobody here plays (idle for walkers, run for most): no gathers
        a, b = m.pivots[r, i], m.pivots[r, i + 1]
        on = w * np.minimum(a[:, 2], b[:, 2])  # a clip whose foot lifts between the two samples does not count
        mx += on * (a[:, 0] + u * (b[:, 0] - a[:, 0]))
        mz += on * (a[:, 1] + u * (b[:, 1] - a[:, 1]))
        down += on
    planted = down >= 0.5
    inv = scale / np.maximum(down, 1e-12)
    mx, mz = mx * inv, mz * inv
    # Model (x, z) to world for a heading (hx, hz), the front: (hz x + hx z, -hx x + hz z).
    dx = (hz0 - hz1) * mx + (hx0 - hx1) * mz
    dz = (hx1 - hx0) * mx + (hz0 - hz1) * mz
    return np.where(planted, dx, 0.0), np.where(planted, dz, 0.0)


@dataclass
class _AgentMotion:
    """The Motion fields the locomotion functions read, per agent (arrays), for a crowd of several
    characters: locomotion_weights, blended_stride and phase_rate take it where they take a Motion."""

    walk_stride: np.ndarray
    run_stride: np.ndarray
    run_speed: np.ndarray
    walk_slowest: np.ndarray
    duration: dict  # {"idle": per agent}


_KIND_FIELDS = ("_m_walk_stride", "_m_run_stride", "_m_run_speed", "_m_walk_slowest", "_m_idle")  # per agent, a cast of several only
