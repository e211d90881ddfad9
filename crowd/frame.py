"""The contracts one frame passes between stages: plain numpy values, each with a ``validate()``.

In the spirit of ozz-animation's jobs, a stage takes these as inputs and writes them as outputs, and
checks them at its door; none of them owns GL objects or imports a stage, so every stage can use them
(the AI writes layers and instances without knowing that a GPU exists).

- **Layers** (``empty_layers``, ``validate_layers``): float32 (agents, layers, 4), one row per layer of
  (clip index, phase, weight, joint mask index). The AI writes them, the animation processor reads them.
- **Joint masks** (``validate_masks``): float32 (masks, joints) factors in [0, 1].
- **Layer overrides** (``LayerOverrides``): what a person forces on top of the AI (a clip played from
  its start, layer weights held at a value), applied by the frame after the AI has written its layers.
- **Instances** (``Instances``): per agent a float64 world position, heading, scale, tint and variation
  pieces, and how many agents each character of the cast has. The AI writes them, the renderer reads them.
- **The cast** (``cast_counts``, ``cast_moves``): a crowd of several characters keeps each one's agents
  together, in the cast's order (agents 0 .. c0 - 1 are the first character's, and so on), so every
  per-character stage works on a slice: the processor dispatches a range, the layers of a range use that
  character's clip indices. The counts come from the shares by one rule, and a resize keeps each
  character's first agents (``cast_moves`` says where each block goes).
- **Camera** (``Camera``): where the frame is seen from. Its projection is the draw stage's
  (``crowd.draw.render.view_proj``), which matches GL's clip conventions.

Every check raises ``FrameError`` with a one-line message.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

import numpy as np

from .errors import CrowdError
from .spans import min_max, over_spans

CLIP, PHASE, WEIGHT, MASK = range(4)  # the columns of one layer
LAYER_COLUMNS = ("clip", "phase", "weight", "mask")
MAX_LAYERS = 4
PHASE_LIMIT = 32.0  # cycles: validate_layers says why
MAX_WEIGHT = 1.0e6  # larger weights would overflow the float32 sum long before they mean anything


class FrameError(CrowdError, ValueError):
    """A frame contract broken by its producer; the message is one line."""


MAX_CAST = 256  # characters in one crowd: an agent's record keeps its character in a byte (crowd.draw.cull_lists)


# -- the cast


def cast_counts(agents: int, shares) -> tuple[int, ...]:
    """How many of `agents` each character gets for its share (shares > 0, any scale: they are
    normalised): the floor of each exact count, and the agents left over to the largest remainders
    (the first character on a tie), so the counts sum to `agents` and each is within 1 of its share."""
    w = np.asarray(shares, np.float64).reshape(-1)
    if not 1 <= w.size <= MAX_CAST or not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise FrameError(f"a cast needs 1 to {MAX_CAST} finite shares above 0, got {list(np.ravel(shares))}")
    exact = agents * (w / w.sum())
    counts = np.floor(exact).astype(np.int64)
    left = int(agents - counts.sum())
    if left > 0:
        counts[np.argsort(-(exact - counts), kind="stable")[:left]] += 1
    return tuple(int(c) for c in counts)


def cast_firsts(counts) -> np.ndarray:
    """(K + 1,) int64: where each character's agents start, and the crowd's size last."""
    return np.concatenate([[0], np.cumsum(np.asarray(counts, np.int64))]).astype(np.int64)


def cast_moves(old, new) -> list[tuple[int, int, int]]:
    """For a crowd resized from counts `old` to `new` (the same cast): per character, (its first agent
    before, after, how many of its agents are kept), the kept ones being its first ones, in order."""
    if len(old) != len(new):
        raise FrameError(f"a resize keeps the cast: {len(old)} characters before, {len(new)} after")
    a, b = cast_firsts(old), cast_firsts(new)
    return [(int(a[k]), int(b[k]), int(min(old[k], new[k]))) for k in range(len(old))]


def move_agents(array: np.ndarray, moves, size: int, fill=0) -> np.ndarray:
    """A new array of `size` agents (the first axis) holding each character's kept block from `array`
    at its new place (``cast_moves``), `fill` elsewhere."""
    out = np.full((size,) + array.shape[1:], fill, array.dtype)
    for before, after, kept in moves:
        out[after:after + kept] = array[before:before + kept]
    return out


# -- layers


def empty_layers(agents: int, layer_count: int = MAX_LAYERS) -> np.ndarray:
    """Layers that contribute nothing (weight 0, whole-body mask): every joint falls back to rest."""
    layers = np.zeros((agents, layer_count, 4), dtype=np.float32)
    layers[..., MASK] = -1.0
    return layers


def validate_layers(layers, clip_count: int, mask_count: int, layer_count: int) -> np.ndarray:
    """Check the layers contract; returns a C-contiguous float32 (N, L, 4) array."""
    a = np.asarray(layers)
    if a.ndim != 3 or a.shape[1] != layer_count or a.shape[2] != 4:
        raise FrameError(f"layers must have shape (agents, {layer_count}, 4), got {a.shape}")
    if not np.issubdtype(a.dtype, np.floating) and not np.issubdtype(a.dtype, np.integer):
        raise FrameError(f"layers must be numeric, got {a.dtype}")
    a = np.ascontiguousarray(a, dtype=np.float32)
    if a.size == 0 or _within_contract(a, clip_count, mask_count):
        return a
    # Something is out of bounds: find it and say which (these passes run only for a bad frame).
    if not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a))[0]
        raise FrameError(f"layers hold NaN or Inf (agent {bad[0]}, layer {bad[1]}, {LAYER_COLUMNS[bad[2]]})")
    # Phases are refused, never rounded, where float32 cannot hold them to within 1e-6 cycles: from
    # |phase| = 32 on, float32's step is 2^-18 cycles or more, so a phase is off by up to 1.9e-6 cycles
    # (up to 0.004 cycles at 1e5 cycles: 24 mm on the run clip). Below 32 the step is at most 2^-19 and
    # a float64 phase rounds to within 9.5e-7 cycles. Refusing rather than carrying a float64 phase: the layers
    # are float32 by contract (the AI writes them in place, the layer texture is RGBA32F), so a producer
    # that sends 1e5 cycles has already rounded them and nothing here could restore the lost digits;
    # wrapping in float64 is the producer's job (crowd.sim.locomotion.advance_phase, LayerOverrides.apply). The
    # limit holds for one-shot clips too: the loop flag can change at run time (set_clip_loop).
    far = np.abs(a[..., PHASE]) >= PHASE_LIMIT
    if np.any(far):
        agent, layer = np.argwhere(far)[0]
        raise FrameError(f"layer phase {float(a[agent, layer, PHASE]):.9g} (agent {agent}, layer {layer}) is not within ±{PHASE_LIMIT:g} "
                         f"cycles, where float32 holds a phase to 1e-6 cycles: wrap looping phases into [0, 1) (and clamp one-shot "
                         f"ones to [0, 1]) in float64 before writing layers")
    clip = a[..., CLIP]
    if np.any(clip != np.round(clip)) or np.any(clip < 0) or np.any(clip >= clip_count):
        raise FrameError(f"layer clip indices must be whole numbers in [0, {clip_count})")
    if float(np.max(a[..., WEIGHT])) > MAX_WEIGHT:
        raise FrameError(f"a layer weight exceeds {MAX_WEIGHT:g} (largest {float(np.max(a[..., WEIGHT])):.3g}); weights are relative, scale them down")
    mask = a[..., MASK]
    if np.any(mask != np.round(mask)) or np.any(mask < -1) or np.any(mask >= mask_count):
        raise FrameError(f"layer masks must be -1 (whole body) or whole numbers in [0, {mask_count})")
    return a


def _within_contract(a: np.ndarray, clip_count: int, mask_count: int) -> bool:
    """Whether C-contiguous float32 layers (N, L, 4) pass every check of ``validate_layers``, from each
    (layer, column)'s minimum and maximum (NaN propagates through both) and a whole-number test of
    the clip and mask columns that vary. The checks one by one took 5.7 ms a frame for 100,000 agents
    on the H200 machine's host (10 passes over the array; docs/BENCHMARKS.md, "The frame before and
    after, same lease"). A column whose minimum is its maximum (the AI's locomotion layers play one
    clip each, with no mask) is whole exactly when that one value is, so only the others (the action
    layer's) are compared with their floor: 2 strided passes instead of 2 per layer."""
    lo, hi = _column_extremes(a)  # (L, 4) each
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        return False
    if max(-float(lo[:, PHASE].min()), float(hi[:, PHASE].max())) >= PHASE_LIMIT or float(hi[:, WEIGHT].max()) > MAX_WEIGHT:
        return False
    if lo[:, CLIP].min() < 0 or hi[:, CLIP].max() >= clip_count or lo[:, MASK].min() < -1 or hi[:, MASK].max() >= mask_count:
        return False
    uneven = []
    for layer in range(a.shape[1]):
        for c in (CLIP, MASK):
            if lo[layer, c] == hi[layer, c]:
                if lo[layer, c] != np.floor(lo[layer, c]):
                    return False
                continue
            uneven.append((layer, c))
    if not uneven:
        return True

    def whole(first: int, last: int) -> bool:  # (finite now: a value is equal to its floor exactly when whole)
        floor = np.empty(last - first, np.float32)
        for layer, c in uneven:
            column = a[first:last, layer, c]
            np.floor(column, out=floor)
            if not np.array_equal(floor, column):
                return False
        return True

    return all(over_spans(whole, len(a)))


def _column_extremes(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each (layer, column)'s minimum and maximum, (L, 4) each, over C-contiguous float32 layers (N, L, 4),
    from spans of agents side by side (crowd.spans)."""
    parts = over_spans(lambda first, last: _span_extremes(a[first:last]), len(a))
    lo = np.min([p[0] for p in parts], axis=0)
    hi = np.max([p[1] for p in parts], axis=0)
    return lo.reshape(a.shape[1:]), hi.reshape(a.shape[1:])


def _span_extremes(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """As ``_column_extremes``, flat (L * 4,), for one span. A column-wise reduction of an (M, 4) array runs
    a 4-wide inner loop (10 ms for 100,000 agents' layers); rows of about 1024 values (whole agents)
    reduce at memory speed, and their partial results fold into the L x 4 after."""
    width = a.shape[1] * a.shape[2]
    if not len(a):
        return np.full(width, np.inf, np.float32), np.full(width, -np.inf, np.float32)
    flat = a.reshape(-1)
    row = 1024 // width * width
    split = flat.size // row * row
    chunks = [c for c in (flat[:split].reshape(-1, row), flat[split:].reshape(-1, width)) if len(c)]
    lo = np.min([c.min(axis=0).reshape(-1, width).min(axis=0) for c in chunks], axis=0)
    hi = np.max([c.max(axis=0).reshape(-1, width).max(axis=0) for c in chunks], axis=0)
    return lo, hi


def validate_masks(masks, joint_count: int) -> np.ndarray | None:
    if masks is None:
        return None
    m = np.asarray(masks, dtype=np.float32)
    if m.ndim == 1:
        m = m[None]
    if m.ndim != 2 or m.shape[1] != joint_count or m.shape[0] == 0:
        raise FrameError(f"joint masks must have shape (masks, {joint_count}), got {np.shape(masks)}")
    if not np.all(np.isfinite(m)) or np.any(m < 0) or np.any(m > 1):
        raise FrameError("joint mask factors must be finite and within [0, 1]")
    return np.ascontiguousarray(m)


@dataclass(frozen=True)
class ForcedClip:
    """A clip played from its start on some agents (None: all), ignoring the AI's choice for layer 0."""

    clip: int  # index into the bake's clips (of `character`'s bake)
    start: float  # simulated seconds (the AI's clock) at which it started
    agents: np.ndarray | None = None  # None: every agent of `character`
    character: int = 0  # whose clip it is: the cast's index


@dataclass(frozen=True)
class LayerOverrides:
    """What a person puts on top of the AI's layers for one frame: the panel's "play" and held weights.

    The frame applies it after the AI has written its layers (``apply``), so the AI never knows, and
    nothing below the session calls back up into it."""

    forced: ForcedClip | None = None
    held: dict = field(default_factory=dict)  # layer → (weight, agents or None for all)

    def __bool__(self) -> bool:
        return self.forced is not None or bool(self.held)

    def validate(self, clip_count: int, layer_count: int = MAX_LAYERS) -> "LayerOverrides":
        if self.forced is not None and not 0 <= self.forced.clip < clip_count:
            raise FrameError(f"forced clip must be an index in [0, {clip_count}), got {self.forced.clip!r}")
        for layer, (weight, _) in self.held.items():
            if isinstance(layer, bool) or not isinstance(layer, numbers.Integral) or not 0 <= layer < layer_count:
                raise FrameError(f"held layer must be 0 to {layer_count - 1}, got {layer!r}")
            if not np.isfinite(weight) or not 0.0 <= weight <= MAX_WEIGHT:
                raise FrameError(f"held weight must be 0 to {MAX_WEIGHT:g}, got {weight!r}")
        return self

    def forced_phase(self, time: float, duration: float, speed: float, loop: bool) -> float:
        """The forced clip's phase at the AI's clock `time`, wrapped (looping) or clamped (one-shot) in
        float64, as crowd.sim.locomotion.advance_phase keeps the AI's own phases. Unwrapped, the float32 layer
        would round 10 hours of a 0.7 s run (51,429 cycles) to the nearest 2^-8 cycle, 4.4 mm off the
        float64 pose (457 mm after 1000 hours, and refused by validate_layers from 32 cycles on);
        wrapped first, the float32 phase is within 3e-8 cycles of the float64 one."""
        if self.forced is None:
            return 0.0
        phase = (float(time) - float(self.forced.start)) * float(speed) / max(float(duration), 1e-6)
        if not loop:
            return min(max(phase, 0.0), 1.0)
        phase -= float(np.floor(phase))
        return 0.0 if phase >= 1.0 else phase  # -1e-20 wraps to 1.0 in float64; 1.0 and 0.0 are the same pose

    def apply(self, layers: np.ndarray, time: float, duration: float, speed: float, loop: bool, within: slice | None = None) -> None:
        """Write the overrides into `layers` in place. `time` is the AI's clock after this frame's step;
        `duration`, `speed` and `loop` describe the forced clip (ignored without one); `within`: the
        agents of the forced clip's character (None: every agent), the only ones it is forced on."""
        n = len(layers)
        if self.forced is not None:
            agents = self.forced.agents
            lo, hi = (0, n) if within is None else (within.start, within.stop)
            agents = slice(lo, hi) if agents is None else agents[(agents >= lo) & (agents < min(hi, n))]
            layers[agents] = (0.0, 0.0, 0.0, -1.0)
            layers[agents, 0, CLIP] = self.forced.clip
            layers[agents, 0, PHASE] = self.forced_phase(time, duration, speed, loop)
            layers[agents, 0, WEIGHT] = 1.0
        for layer, (weight, agents) in self.held.items():
            agents = slice(None) if agents is None else agents[agents < n]
            layers[agents, layer, WEIGHT] = weight


# -- the sim stage's output on the GPU


@dataclass
class SimFrame:
    """What the GPU AI (crowd.sim.gpu) hands the later stages in a frame, in place of ``Instances`` and
    the layers: its state buffers (GPU buffers by name, laid out as crowd.sim.gpu.state says), the agent
    rows they hold (`agents`, each character's block in `cast`), and the rows the stages draw (`rows`:
    the crowd's and, after them, the survivor's, whose instance comes from the CPU in `extra`). Nothing in
    it is read by the CPU; the read-back facts arrive apart (crowd.sim.gpu.facts)."""

    agents: int
    cast: tuple
    buffers: dict  # name -> GPU buffer of the AI's state (crowd.sim.gpu.state.FIELDS)
    origin: np.ndarray  # float64 (x, z): the positions in the buffers are relative to it
    steps: int  # the AI's step() count: an agent whose spawned_step is above a frame's count was not there then
    extra: "Instances | None" = None  # the survivor's row, drawn after the crowd's
    max_scale: float = 1.0  # the largest agent scale (the shadows' reach upward)

    @property
    def rows(self) -> int:
        return self.agents + (0 if self.extra is None else len(self.extra))

    def counts(self) -> tuple:
        """Agents of each character the stages draw: the crowd's blocks, then the survivor's."""
        return tuple(self.cast) + (() if self.extra is None else (len(self.extra),))


# -- instances and the camera


@dataclass
class Instances:
    position: np.ndarray  # float64 (N, 3) world position of the agent's origin (on the ground)
    yaw: np.ndarray  # float32 (N,) heading about +Y, radians
    scale: np.ndarray  # float32 (N,)
    tint: np.ndarray  # uint8 (N, 4)
    variant: dict[str, np.ndarray] = field(default_factory=dict)  # group → (N,) index into the group's pieces of the agent's character
    cast: tuple[int, ...] | None = None  # agents of each character, in the cast's order (None: one character)

    def __len__(self) -> int:
        return int(self.position.shape[0])

    def counts(self) -> tuple[int, ...]:
        """Agents of each character (one character: all of them)."""
        return (len(self),) if self.cast is None else tuple(self.cast)

    def validate(self, groups) -> "Instances":
        """`groups`: per character (a list, in the cast's order) or for the one character (a dict),
        group → its pieces; a variant index must be below its agent's character's choices."""
        n = len(self)
        if self.position.shape != (n, 3) or self.yaw.shape != (n,) or self.scale.shape != (n,) or self.tint.shape != (n, 4):
            raise FrameError("instances need position (N, 3), yaw (N,), scale (N,) and tint (N, 4)")
        counts = self.counts()
        if any(c < 0 for c in counts) or sum(counts) != n:
            raise FrameError(f"the cast's agent counts {list(counts)} must be whole numbers >= 0 that sum to the {n} instances")
        per_character = [groups] * len(counts) if isinstance(groups, dict) else list(groups)
        if len(per_character) != len(counts):
            raise FrameError(f"instances of {len(counts)} characters drawn by a cast of {len(per_character)}")
        # Finite exactly when the minimum and maximum are (NaN propagates through both): reductions
        # without the boolean temporaries of np.isfinite, a frame's largest check after the layers'.
        extremes = [min_max(a) if n else (0.0, 1.0) for a in (self.position, self.yaw, self.scale)]
        if not all(math.isfinite(lo) and math.isfinite(hi) for lo, hi in extremes):
            raise FrameError("instance positions, headings and scales must be finite")
        if n and (extremes[2][0] <= 0 or extremes[2][1] > 100):
            raise FrameError("instance scales must be in (0, 100]")
        firsts = cast_firsts(counts)
        for group, v in self.variant.items():
            if not any(group in g for g in per_character):
                continue  # a group nobody draws (a piece left out)
            if v.shape != (n,):
                raise FrameError(f"variant of group {group!r} must be (N,) indices, got {v.shape}")
            for k, character_groups in enumerate(per_character):
                part = v[firsts[k]:firsts[k + 1]]
                choices = len(character_groups.get(group, ())) or 1  # a character without the group: 0 only
                low, high = min_max(part)
                if part.size and (low < 0 or high >= choices):
                    raise FrameError(f"variant of group {group!r} must be indices below {choices}"
                                     + (f" for character {k}" if len(per_character) > 1 else ""))
        return self


@dataclass
class Camera:
    eye: np.ndarray  # float64 (3,)
    target: np.ndarray  # float64 (3,)
    fov_y: float = 45.0  # degrees
    near: float = 0.1
    far: float = 400.0
    aspect: float = 16 / 9
    # Metres at which the fog has hidden 95 % of what is there; None: the lighting's own (crowd.lighting).
    # The view of the horde to its far side thins it (crowd.cameras.horizon_camera).
    fog_reach: float | None = None

    def validate(self) -> "Camera":
        eye, target = np.asarray(self.eye, np.float64), np.asarray(self.target, np.float64)
        if eye.shape != (3,) or target.shape != (3,) or not np.all(np.isfinite(eye)) or not np.all(np.isfinite(target)):
            raise FrameError("camera eye and target must be finite 3-vectors")
        if np.linalg.norm(target - eye) < 1e-6:
            raise FrameError("camera eye and target coincide")
        if not 0 < self.near < self.far or not 1.0 <= self.fov_y <= 170.0 or not self.aspect > 0:
            raise FrameError("camera needs 0 < near < far, a field of view of 1 to 170 degrees and a positive aspect")
        if self.fog_reach is not None and not (0.0 < float(self.fog_reach) < math.inf):
            raise FrameError(f"camera fog reach must be a positive number of metres or None, got {self.fog_reach}")
        return self
