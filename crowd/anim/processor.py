"""Process stage: per-agent animation layers → the FinalAnimationTexture of skinning matrices, on the GPU.

Contract (the shape of an ozz-animation job: validated inputs, documented edge cases):

input ``layers``: float32 (N, L, 4) with L = the processor's layer count (1..4); per layer
  ``[clip, phase, weight, mask]`` (column constants CLIP, PHASE, WEIGHT, MASK):
  - clip: index into the bake's clips (integer valued);
  - phase: within ±32 cycles, where float32 holds it to 1e-6 cycles (validate_layers refuses the rest,
    in one line, rather than round it); looping clips wrap it into [0, 1), one-shot clips clamp it to
    [0, 1]. Producers wrap in float64 first (crowd.sim.ai.advance_phase, LayerOverrides.apply);
  - weight: finite, at most MAX_WEIGHT; negative weights count as 0; weights need not sum to 1;
  - mask: -1 for the whole body, else a row of the processor's joint masks (factor per joint in [0, 1]).
  Per joint, as crowd.anim.reference.blend (its docstring says why each rule), with S the sum of the
  layers' max(weight, 0) (only ratios of weights matter): weights are multiplied by the mask; each
  layer samples its keys as the interpolation says (INTERPOLATIONS below: by default rotation nlerp at
  a weight corrected to track slerp, and translation lerp); rotations are sign-aligned to the anchor,
  the first-listed layer with a weight above 0 at that joint, and their weighted sum normalised (the
  anchor's rotation where the sum is shorter than CANCELLED_NORM times S), translations and scales are weighted means (dq_lerp
  instead sums the dual quaternions); a joint whose masked weights add up to less than REST_THRESHOLD
  times S takes the rest pose. Then the hierarchy is concatenated and multiplied by the inverse bind.

output: the palette, three RGBA32F array textures ("planes") holding rows 0, 1 and 2 of each 3x4
  skinning matrix. Agent a, joint j lives at texel ((a % agents_per_row) * J + j, y) of each plane,
  with y = a // agents_per_row + the ring slot's first row: one palette row per agent, several agents
  side by side in a texture row (under 4096 texels wide). Palette rows are counted across the planes'
  layers, ``layer_rows`` to a layer (shaders/palette.glsl): row y is texture row y % layer_rows of
  layer y // layer_rows. A layer is as tall as one ring slot needs, up to the driver's texture size,
  and a slot taller than that spans several layers, so a million agents fit wherever the memory does
  (a 2D texture stopped at 16,384 rows on llvmpipe: 2.9 million agents of 23 joints, or 262,000 with a
  history of 4 and 64 joints). The GL 3.3 path needs the planes: multiple render targets write the
  same pixel of several attachments, so the three texels of a joint sit at one coordinate of three
  textures. The compute path writes the same planes, so the renderers do not care which path ran.
  Readers address a texel by one code, x | y << 12 (``texel_code``), so y may reach 2^20 rows.

history: with ``history`` = H > 1 the planes hold H palettes stacked vertically (a ring): each run
  writes the next slot, and the palettes of the H - 1 runs before stay readable. The weapons' readback
  uses it to draw each body with the palette of the frame whose sockets the CPU has read
  (``row_offset(age)`` is where the palette of `age` runs ago starts). H = 1 (no weapons) keeps one.

foot lock: a processor built with ``legs`` (crowd.anim.foot_lock) holds each planted foot where it came
  down, between the blend and the composition, with a state per agent and leg that the next run reads;
  ``upload`` then also takes each agent's motion (N, 4: ground step x, z since the last run, and front x,
  z times its scale) and the frame's simulated seconds. Compute path only.

Paths: "compute" (GL 4.3, one dispatch) and "fragment" (GL 3.3, two draws: every joint's blended local
into a scratch of one ring slot's shape, then each joint's chain composed from it); "auto" takes compute
where the context has GL 4.3. Both run the same GLSL (shaders/processor_common.glsl).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import moderngl
import numpy as np

from .. import transforms as tf
from ..frame import CLIP, MASK, MAX_LAYERS, PHASE, WEIGHT, FrameError, validate_layers, validate_masks
from .bake import AnimationBake
from .compress import PER_KEY
from . import foot_lock as lock
from ..gl import GLStage, gpu_bytes, has_compute, limit_note, load_shader
from ..settings import DEFAULTS, SETTINGS
from ..spans import min_max, over_spans
from .morph import ACTIVE_WEIGHT, MAX_MORPH_WEIGHT, MORPH_PAIRS, NOT_HELD
from .reference import CANCELLED_NORM, REST_THRESHOLD, aligned_sign

LOCALS_UNITS = (12, 13, 14)  # the fragment path's scratch of blended locals, read by its compose pass
MAX_JOINTS = 256  # one compute work group of 256 invocations holds at least one whole agent
GROUP_SIZE = 256
# How one layer turns its two (or four) neighbouring baked keys into a local transform, and how layers
# blend (crowd-bench error measures each; docs/BENCHMARKS.md says why the default is the default):
# - dq_lerp: the DQ keys lerped blindly and normalised; layers blended as dual quaternions (DLB);
# - qt_lerp: each key split into rotation and translation; rotations nlerped, translations lerped;
#   layers blended the same way (ozz-animation's blending job, and the float64 reference's semantics);
# - qt_corrected: as qt_lerp, with the nlerp's weight corrected so that it tracks slerp (below);
# - qt_cubic: as qt_lerp, with Catmull-Rom through four keys instead of the lerp between two.
INTERPOLATIONS = SETTINGS["interpolation"].choices
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


DEFAULT_INTERPOLATION = DEFAULTS["interpolation"]  # chosen by crowd-bench error: see docs/BENCHMARKS.md
# Agents side by side in one palette texture row: keeps textures under 4096 texels wide, a size every
# GL 3.3+ driver we target accepts (GL_MAX_TEXTURE_SIZE is 16384 on llvmpipe, 32768 on NVIDIA).
MAX_TEXTURE_WIDTH = 1 << 12
MAX_HISTORY = SETTINGS["readback_latency"].high + 1  # palettes kept: the latest and one per frame of read-back latency


class ProcessorError(ValueError):
    """Bad processor input; the message is one line."""


TEXEL_ROW_SHIFT = 12  # a texel code is x | y << 12: x < MAX_TEXTURE_WIDTH = 2^12, y < 2^20 palette rows
MAX_PALETTE_ROWS = 1 << (32 - TEXEL_ROW_SHIFT)


def palette_texel(agents, joints, row_offset, agents_per_row: int, joint_count: int) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) int64 texel of joint(s) `joints` of `agents` in a palette plane, in the ring slot that
    starts at row `row_offset` (an int, or one per agent); y counts rows across layers. The one
    statement of the palette layout."""
    agents = np.asarray(agents, np.int64)
    return (agents % agents_per_row) * joint_count + np.asarray(joints, np.int64), agents // agents_per_row + np.asarray(row_offset, np.int64)


def palette_limits(ctx: moderngl.Context) -> tuple[int, int]:
    """(texture rows a palette layer may have, layers an array texture may have) on this context."""
    return int(ctx.info.get("GL_MAX_TEXTURE_SIZE", 16384)), int(ctx.info.get("GL_MAX_ARRAY_TEXTURE_LAYERS", 256))


def texel_code(x, y) -> np.ndarray:
    """uint32 code of palette texels (x, y), as shaders/palette.glsl reads it."""
    return np.asarray(x, np.uint32) | (np.asarray(y, np.uint32) << np.uint32(TEXEL_ROW_SHIFT))


def resolve_path(ctx: moderngl.Context, path: str, limit: int | None = None) -> str:
    """The processor path "auto" takes on this context: compute where it has GL 4.3 and `limit` (the "gl"
    setting's: crowd.gl.feature_level) lets the stages use it, else fragment. "compute" where they may not: ProcessorError."""
    compute = has_compute(ctx, limit)
    if path == "compute" and not compute:
        raise ProcessorError(f"the compute path needs GL 4.3, this context has {ctx.version_code}{limit_note(ctx, limit)}")
    return ("compute" if compute else "fragment") if path == "auto" else path


def check_motion(motion, agents: int) -> np.ndarray:
    """The foot lock's per-agent motion (N, 4) float32: ground step x, z and front x, z times the scale,
    all finite, the front not 0."""
    if motion is None:
        raise ProcessorError("the foot lock needs each agent's motion (ground step x, z, front x, z times scale) with its layers")
    m = np.ascontiguousarray(motion, np.float32)
    if m.shape != (agents, 4):
        raise ProcessorError(f"agent motion must be ({agents}, 4) (ground step x, z, front x, z times scale), got {np.shape(motion)}")
    # Two reductions where every value is fine (min and max carry NaN and infinities); the row is found only for the message.
    if m.size and not all(math.isfinite(v) for v in min_max(m)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(m), axis=1))[0])
        raise ProcessorError(f"agent motion of agent {bad} is not finite: {m[bad].tolist()}")

    def shortest(lo: int, hi: int) -> float:  # the shortest front's squared length in a span (crowd.spans)
        front = m[lo:hi, 2] * m[lo:hi, 2]
        front += m[lo:hi, 3] * m[lo:hi, 3]
        return float(front.min()) if hi > lo else math.inf

    if len(m) and not min(over_spans(shortest, len(m))) > 1e-24:
        front = m[:, 2] * m[:, 2] + m[:, 3] * m[:, 3]
        bad = int(np.flatnonzero(~(front > 1e-24))[0])
        raise ProcessorError(f"agent {bad} has front {m[bad, 2:].tolist()} times its scale; the foot lock needs one of length > 0")
    return m


def check_interpolation(interpolation) -> str:
    return SETTINGS["interpolation"].check(interpolation, ProcessorError)


def _check_history(history) -> int:
    if isinstance(history, bool) or not isinstance(history, (int, np.integer)) or not 1 <= history <= MAX_HISTORY:
        raise ProcessorError(f"palette history must be a whole number from 1 to {MAX_HISTORY}, got {history!r}")
    return int(history)


def _translation(real: np.ndarray, dual: np.ndarray) -> np.ndarray:
    """Translation of stored DQ keys (f16 keys are not exactly unit: dq_to_rt normalises first)."""
    return tf.dq_to_rt(real, dual)[1]


def _catmull_rom(p0, p1, p2, p3, u):
    """Uniform Catmull-Rom between p1 and p2; u broadcasts against the keys' leading axes."""
    return p1 + u * (0.5 * (p2 - p0) + u * ((p0 - 2.5 * p1 + 2.0 * p2 - 0.5 * p3) + u * (0.5 * (p3 - p0) + 1.5 * (p1 - p2))))


def _sample_keys(texels, scales, table, clip, phase, interpolation):
    """One layer's local transform of every joint, float64, as the shader samples it. Returns
    (rotation or DQ real (N, J, 4), translation (N, J, 3) or DQ dual (N, J, 4), scale (N, J))."""
    first, count, _, loop = table[clip].T
    looping = loop > 0.5
    phase = np.where(looping, phase - np.floor(phase), np.clip(phase, 0.0, 1.0))
    f = phase * (count - 1.0)
    i0 = np.clip(np.floor(f), 0.0, count - 2.0)
    u = (f - i0)[:, None, None]
    row = (first + i0).astype(np.int64)

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
    return (glob @ bake.inverse_bind()[None])[:, :, :3, :]


def palette_joint_positions(palette_rows: np.ndarray, inverse_bind: np.ndarray) -> np.ndarray:
    """Model-space joint positions from skinning matrix rows (N, J, 3, 4): skin × bind, translation."""
    bind = np.linalg.inv(np.asarray(inverse_bind, dtype=np.float64))
    rows = np.asarray(palette_rows, dtype=np.float64)
    return np.einsum("njrc,jc->njr", rows, bind[:, :, 3])


@dataclass(frozen=True)
class PalettePart:
    """One character's block of a palette ring slot: its agents (first_agent .. first_agent + count - 1),
    agents_per_row of them side by side in a texture row, each `width` texels wide (`slots` texels before
    its `joints`: its impostor key where impostors are drawn (crowd.draw.impostors), then its morph pairs
    where `morph` (crowd.anim.morph)), from row first_row."""

    first_agent: int
    count: int
    joints: int
    agents_per_row: int
    first_row: int
    slots: int = 0
    morph: bool = False  # the texel before joint 0 holds the agent's morph pairs

    @property
    def key(self) -> bool:
        """Whether the agent's first texel holds its impostor key (the clip and phase its impostor shows)."""
        return self.slots > int(self.morph)

    @property
    def rows(self) -> int:
        return math.ceil(self.count / self.agents_per_row)

    @property
    def width(self) -> int:
        return self.slots + self.joints


@dataclass(frozen=True)
class PaletteLayout:
    """Where each agent's skinning matrices live in a palette ring slot: every character of the cast has
    a block of rows of its own, laid out for its own joint count (no texel spent on a larger skeleton's
    joints), one after the other in the cast's order. The one statement of the layout: the processor
    writes by it, the instance records and the read-back address by it (``texel``)."""

    parts: tuple[PalettePart, ...]

    @staticmethod
    def make(joint_counts, counts, slots=None, morphs=None) -> "PaletteLayout":
        """`slots`: each character's texels before an agent's joints (None: none); `morphs`: whether the
        last of them holds morph pairs (None: wherever there is a slot)."""
        parts, agent, row = [], 0, 0
        slots = slots or [0] * len(joint_counts)
        morphs = morphs if morphs is not None else [s > 0 for s in slots]
        for joints, count, s, m in zip(joint_counts, counts, slots, morphs):
            part = PalettePart(agent, int(count), int(joints), max(1, MAX_TEXTURE_WIDTH // (int(joints) + int(s))), row, int(s), bool(m))
            parts.append(part)
            agent += part.count
            row += part.rows
        return PaletteLayout(tuple(parts))

    @property
    def agents(self) -> int:
        return sum(p.count for p in self.parts)

    @property
    def rows(self) -> int:
        """Palette rows one ring slot holds."""
        return sum(p.rows for p in self.parts)

    @property
    def width(self) -> int:
        """Texels a palette row has: the widest character's (constant for a cast, whatever its counts)."""
        return max(p.agents_per_row * p.width for p in self.parts)

    @property
    def counts(self) -> tuple[int, ...]:
        return tuple(p.count for p in self.parts)

    def part_of(self, agents) -> np.ndarray:
        """Index of the part (character) of each of `agents`."""
        firsts = np.array([p.first_agent + p.count for p in self.parts[:-1]], np.int64)
        return np.searchsorted(firsts, np.asarray(agents, np.int64), side="right")

    def texel(self, agents, joints, row_offset=0) -> tuple[np.ndarray, np.ndarray]:
        """(x, y) int64 palette texel of joint(s) `joints` of `agents` (global numbers) in the ring slot
        that starts at row `row_offset` (an int, or one per agent); y counts rows across layers."""
        agents = np.asarray(agents, np.int64)
        if len(self.parts) == 1:
            p = self.parts[0]
            x, y = palette_texel(agents, np.asarray(joints, np.int64) + p.slots, row_offset, p.agents_per_row, p.width)
            return x, y + p.first_row
        k = self.part_of(agents)
        table = np.array([(p.first_agent, p.agents_per_row, p.width, p.first_row, p.slots) for p in self.parts], np.int64)
        first, per_row, width, first_row, slots = (table[k, c] for c in range(5))
        local = agents - first
        return ((local % per_row) * width + slots + np.asarray(joints, np.int64),
                first_row + local // per_row + np.asarray(row_offset, np.int64))

    def agents_at(self, x, y) -> np.ndarray:
        """The agents whose joints' texels (x, y) are, y counted from their ring slot's first row: the
        inverse of ``texel`` (tests and benchmarks read the lists back by it)."""
        x, y = np.asarray(x, np.int64), np.asarray(y, np.int64)
        table = np.array([(p.first_agent, p.agents_per_row, p.width, p.first_row) for p in self.parts], np.int64)
        k = np.searchsorted(table[:, 3], y, side="right") - 1
        return table[k, 0] + (y - table[k, 3]) * table[k, 1] + x // table[k, 2]


class _Part:
    """One character's share of the processor: its bake's textures, program and foot-lock state."""

    def __init__(self, bake: AnimationBake, masks, legs, key: bool = False):
        self.bake = bake
        self.masks = masks
        self.legs = legs
        self.key = bool(key)  # an impostor key texel first (crowd.draw.impostors)
        self.morph = bake.morphs is not None  # a texel of morph pairs before an agent's joints
        self.slots = int(self.key) + int(self.morph)
        # Morph weights held from the panel: (M,) float32, -1 where not held, and whose (crowd.anim.morph.ALL_HELD,
        # NOT_HELD, or an agent's number among the character's).
        self.held = None if bake.morphs is None else np.full(bake.morphs.count, -1.0, np.float32)
        self.held_agent = NOT_HELD
        self.held_written = None  # the held weights the texture holds
        self.program = None
        self.textures: dict = {}
        self.lock_state = self.lock_motion = None
        self.quad = self.quad_vao = None
        self.locals_program = self.locals_vao = None  # the fragment path's first draw (LOCALS_PASS) and its quads
        self.quad_vertices = 0


class AnimationProcessor(GLStage):
    """Owns every character's bake textures, the layers texture and the palette planes, and releases them.

    A crowd of several characters (``bakes`` a sequence) is processed one character at a time, each over
    its own range of agents (the cast's contiguous blocks, crowd.frame): a dispatch (or draw) per
    character, with that character's textures and program, into that character's block of the one
    palette (``layout``)."""

    def __init__(self, ctx: moderngl.Context, bakes, layer_count: int = MAX_LAYERS, masks=None, path: str = "auto",
                 history: int = 1, interpolation: str = DEFAULT_INTERPOLATION, legs=None, impostor_keys=None):
        """`bakes`: one AnimationBake, or one per character of the cast; `masks` and `legs` likewise (one
        value for one bake, a sequence of them for several). `impostor_keys`: per character, whether its
        agents' rows start with the key their impostors are drawn by (None: no character's do)."""
        self._own: dict[str, list] = {"animation": [], "palette": [], "layers": [], "locals": [], "processor_quad": [], "foot_lock": [], "morphs": []}
        self.parts: list[_Part] = []
        self._programs: dict[str, moderngl.Program] = {}
        single = isinstance(bakes, AnimationBake)
        bakes = [bakes] if single else list(bakes)
        masks = [masks] if single else list(masks if masks is not None else [None] * len(bakes))
        legs = [legs] if single else list(legs if legs is not None else [None] * len(bakes))
        if not bakes or len(masks) != len(bakes) or len(legs) != len(bakes):
            raise ProcessorError(f"the processor needs a bake per character, and as many masks and legs ({len(bakes)} bakes, "
                                 f"{len(masks)} masks, {len(legs)} legs)")
        SETTINGS["processor"].check(path, ProcessorError)
        if not 1 <= layer_count <= MAX_LAYERS:
            raise ProcessorError(f"layer count must be 1 to {MAX_LAYERS}, got {layer_count}")
        for bake in bakes:
            jc = bake.joint_count
            if not 1 <= jc <= MAX_JOINTS:
                raise ProcessorError(f"the processor handles 1 to {MAX_JOINTS} joints, this skeleton has {jc}")
            if np.any(bake.parents >= np.arange(jc)):
                raise ProcessorError("the hierarchy must list parents before their children")
        path = resolve_path(ctx, path)  # (refuses "compute" without GL 4.3)
        # The foot lock (crowd.anim.foot_lock): legs given and found, on the compute path, whose shared
        # memory holds an agent's locals between the blend and the composition.
        legs = [l if l is not None and len(l) else None for l in legs]
        if any(l is not None for l in legs) and path != "compute":
            raise ProcessorError("the foot lock runs on the compute path (GL 4.3); the fragment path has no state to keep it in")
        self._lock_dt = 0.0  # the simulated seconds of the frame the last upload was for
        self.ctx = ctx
        self.path = path
        self.layer_count = layer_count
        self.interpolation = check_interpolation(interpolation)
        self.history = _check_history(history)
        # The layers texture's own layout: agents side by side, LAYERS texels each, whatever their skeleton.
        self.layer_agents_per_row = MAX_TEXTURE_WIDTH // layer_count
        self.runs = 0  # runs since the palette was last (re)allocated: slots older than this hold nothing
        self.layer_rows = 1  # texture rows per layer of the planes
        self.slot_layers = 1  # layers one ring slot spans
        self.layers_texture = None
        self._layer_unpack = None  # (the layer rows' pixel-unpack buffer, made with the texture)
        self._locals, self._locals_framebuffer = (), None  # (the fragment path's scratch of blended locals)
        self.planes: tuple = ()
        self._framebuffer = None
        keys = list(impostor_keys) if impostor_keys is not None else [False] * len(bakes)
        if len(keys) != len(bakes):
            raise ProcessorError(f"impostor keys for {len(keys)} characters, the processor has {len(bakes)} bakes")
        for bake, m, l, key in zip(bakes, masks, legs, keys):
            part = _Part(bake, validate_masks(m, bake.joint_count), l, key)
            self.parts.append(part)
            self._make_part(part)
        self.layout = self._layout([0] * len(self.parts))
        self.agents = 0

    # -- what the stages and tests read

    @property
    def bakes(self) -> list[AnimationBake]:
        return [p.bake for p in self.parts]

    @property
    def legs(self):
        """Each character's legs the foot lock holds (None for a character without), or None where the
        lock runs for nobody."""
        legs = tuple(p.legs for p in self.parts)
        return None if all(l is None for l in legs) else legs

    @property
    def masks(self) -> tuple:
        return tuple(p.masks for p in self.parts)

    @property
    def anim_texture(self) -> moderngl.Texture:
        """The first character's AnimationTexture (tests)."""
        return self.parts[0].textures["u_anim"]

    # -- resources

    def _make_part(self, part: _Part) -> None:
        """A character's textures and program (programs with the same source are shared)."""
        bake, jc = part.bake, part.bake.joint_count
        compressed = bake.packed is not None
        dtype = "f2" if bake.precision == "f16" else "f4"
        anim_rows = bake.gpu_texels
        t = part.textures
        t["u_anim"] = self._texture("animation", (2 * jc, anim_rows.shape[0]), 4, anim_rows, dtype)
        if bake.scale is not None:
            t["u_anim_scale"] = self._texture("animation", (jc, bake.rows), 1, bake.scale, dtype)
        if compressed:
            words = bake.packed.word_texture
            t["u_keys"] = self._texture("animation", (words.shape[1], words.shape[0]), 1, words, "u4")
            headers = bake.packed.header_texture
            t["u_tracks"] = self._texture("animation", (4 * jc, headers.shape[0]), 4, headers, "u4")
        t["u_parents"] = self._texture("animation", (jc, 1), 1, bake.parents.astype(np.int32), "i4")
        t["u_clips"] = self._texture("animation", (len(bake.clips), 1), 4, bake.clip_table, "f4")
        if part.masks is not None:
            t["u_masks"] = self._texture("animation", (jc, part.masks.shape[0]), 1, part.masks, "f4")
        defines = {"LAYERS": self.layer_count, "REST_THRESHOLD": f"{REST_THRESHOLD:.1e}", "CANCELLED_NORM": f"{CANCELLED_NORM:.1e}",
                   "MAX_JOINTS": MAX_JOINTS, "ROW_SLOTS": part.slots}
        if part.key:
            defines["IMPOSTOR_KEY"] = 1
        morphs = bake.morphs
        if morphs is not None:  # the morph weight tracks (crowd.anim.morph): only where the scene moves a target
            if len(morphs.clip_rows) != len(bake.clips):
                raise ProcessorError(f"the morph bake has {len(morphs.clip_rows)} clips, the joint bake {len(bake.clips)}")
            t["u_morph_tracks"] = self._texture("morphs", (morphs.count, morphs.tracks.shape[0]), 1, morphs.tracks, "f4")
            t["u_morph_clips"] = self._texture("morphs", (len(bake.clips), 1), 2, morphs.clip_rows.astype(np.int32), "i4")
            t["u_morph_variation"] = self._texture("morphs", (morphs.count, 1), 2, morphs.variation, "f4")
            t["u_morph_held"] = self._texture("morphs", (morphs.count, 1), 1, part.held, "f4")
            part.held_written = part.held
            defines.update(MORPHS=1, MORPH_COUNT=morphs.count, MORPH_PAIRS=MORPH_PAIRS, ACTIVE_WEIGHT=f"{ACTIVE_WEIGHT!r}",
                           MAX_MORPH_WEIGHT=f"{MAX_MORPH_WEIGHT!r}")
        if bake.scale is not None:
            defines["HAS_SCALE"] = 1
        if compressed:
            defines["COMPRESSED"] = 1
            defines["PER_KEY"] = f"{PER_KEY}u"
        if part.masks is not None:
            defines["HAS_MASKS"] = 1
        if part.legs is not None:
            defines.update(FOOT_LOCK=1, LEG_COUNT=len(part.legs), CORRECTION_EPS=f"{lock.CORRECTION_EPS:.1e}",
                           **{name: repr(float(getattr(lock, name))) for name in ("CONTACT_M", "STEP_SHIFT_M", "STEP_TWIST_RAD", "HOLD_SHIFT_M",
                                                                                  "HOLD_TWIST_RAD", "STEP_LIFT_M", "RESET_M", "RESET_RAD",
                                                                                  "MIN_FORWARD_HORIZONTAL")})
        if self.interpolation != "dq_lerp":
            defines["INTERPOLATION_QT"] = 1
        if self.interpolation == "qt_cubic":
            defines["INTERPOLATION_CUBIC"] = 1
        if self.interpolation == "qt_corrected":
            defines["INTERPOLATION_CORRECTED"] = 1
            defines["SLERP_FIT_A"] = "vec3({:.12f}, {:.12f}, {:.12f})".format(*SLERP_FIT[:3])
            defines["SLERP_FIT_B"] = "vec3({:.12f}, {:.12f}, {:.12f})".format(*SLERP_FIT[3:])
        if self.path == "compute":
            source = load_shader("processor.comp.glsl", defines)
            if source not in self._programs:
                self._programs[source] = self.ctx.compute_shader(source)
        else:
            for pass_defines in ({**defines, "LOCALS_PASS": 1}, defines):
                source = load_shader("processor.frag.glsl", pass_defines)
                if source not in self._programs:
                    self._programs[source] = self.ctx.program(vertex_shader=load_shader("processor.vert.glsl"),
                                                              geometry_shader=load_shader("processor.geom.glsl"), fragment_shader=source)
                if "LOCALS_PASS" in pass_defines:
                    part.locals_program = self._programs[source]
        part.program = self._programs[source]
        stride = part.slots + jc
        if stride > GROUP_SIZE:
            raise ProcessorError(f"{jc} joints and a morph slot need {stride} invocations an agent; a work group has {GROUP_SIZE}")
        part.uniforms = {"u_joints": jc, "u_stride": stride, "u_agents_per_group": GROUP_SIZE // stride, "u_rest_row": anim_rows.shape[0] - 1,
                         "u_rest_scale_row": bake.rest_row, "u_layer_agents_per_row": self.layer_agents_per_row}
        if morphs is not None:
            part.uniforms.update(u_morph_seed=morphs.seed, u_character=self.parts.index(part))
        if compressed:
            part.uniforms["u_key_width"] = words.shape[1]
        if part.legs is not None:
            part.leg_bytes = {"u_leg_joints": np.ascontiguousarray(part.legs.joints, np.int32).tobytes(),
                              "u_leg_toe": np.ascontiguousarray(part.legs.toe, np.int32).tobytes(),
                              "u_leg_forward": np.ascontiguousarray(part.legs.forward, np.float32).tobytes(),
                              "u_leg_lowest": np.ascontiguousarray(part.legs.lowest, np.float32).tobytes()}

    def _texture(self, group, size, components, data, dtype):
        tex = self.ctx.texture(size, components, None if data is None else np.ascontiguousarray(data).tobytes(), dtype=dtype)
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._own[group].append(tex)
        return tex

    @staticmethod
    def _set(program, name, value):
        if name in program:
            program[name] = value

    def _release_group(self, group):
        for obj in self._own[group]:
            obj.release()
        self._own[group] = []

    def palette_rows(self, agents=None) -> int:
        """Palette rows the agents fill (one ring slot's); `agents`: counts per character (default the current)."""
        if agents is None:
            return self.layout.rows
        return self._layout(self._counts(agents)).rows

    def slot_rows(self) -> int:
        """Palette rows from one ring slot's start to the next's: its layers' rows."""
        return self.slot_layers * self.layer_rows

    def row_offset(self, age: int = 0) -> int:
        """First palette row (counted across layers) of the palette written `age` runs ago (0: the latest run)."""
        if not 0 <= age < min(self.history, max(self.runs, 1)):
            raise ProcessorError(f"no palette from {age} runs ago (history {self.history}, {self.runs} runs since allocation)")
        return ((self.runs - 1 - age) % self.history) * self.slot_rows()

    def set_history(self, history: int) -> None:
        """Keep `history` palettes (1 to MAX_HISTORY); the planes are reallocated, so older runs are lost."""
        history = _check_history(history)
        if history != self.history:
            self.history = history
            self._allocate(self.layout.counts)

    def _layout(self, counts) -> PaletteLayout:
        """The palette's layout for `counts` agents per character (each with its morph slots, if any)."""
        return PaletteLayout.make([p.bake.joint_count for p in self.parts], counts, [p.slots for p in self.parts], [p.morph for p in self.parts])

    def _counts(self, agents) -> tuple[int, ...]:
        """Agent counts per character from a count (one character) or a sequence of them, checked."""
        counts = (agents,) if isinstance(agents, (int, np.integer)) and not isinstance(agents, bool) else tuple(agents) \
            if isinstance(agents, (tuple, list)) else None
        if counts is None or len(counts) != len(self.parts) or any(
                isinstance(c, bool) or not isinstance(c, (int, np.integer)) or c < 0 for c in counts):
            raise ProcessorError(f"agent count must be a whole number >= 0 per character ({len(self.parts)} of them), got {agents!r}")
        return tuple(int(c) for c in counts)

    def resize(self, agents) -> None:
        """Make room for exactly `agents` agents (a count, or one per character); everything for agents no
        longer there is released. The agents kept (each character's first ones, crowd.frame.cast_moves)
        keep their palette history: new planes get the kept rows copied across on the GPU (so weapons
        stay in hand through it), and their foot-lock state."""
        counts = self._counts(agents)
        old = self.layout
        try:
            new = self._layout(counts)
            if new.rows == old.rows and self.planes and new.agents and all(a.first_row == b.first_row for a, b in zip(old.parts, new.parts)):
                self.layout, self.agents = new, new.agents  # the same texture rows: the agents kept keep their palette history
                if self.layers_texture.height != math.ceil(new.agents / self.layer_agents_per_row):
                    self._make_layers(new.agents)  # (the layers' own rows may still differ: 2,048 agents a row)
                self._update_quads()
                return
            self._allocate(counts, keep=True)
        finally:
            self._resize_lock(old.counts, self.layout.counts)

    def _resize_lock(self, old: tuple[int, ...], new: tuple[int, ...]) -> None:
        """Each character's foot-lock state (a vec4 per agent and leg) and motion (a vec4 per agent)
        buffers: its agents kept keep their state, new ones start free with nothing carried."""
        for part, agents in zip(self.parts, new):
            if part.legs is None:
                continue
            size = agents * len(part.legs) * 16
            if part.lock_state is not None and part.lock_state.size == size and agents:
                continue
            was, objects = part.lock_state, [o for o in (part.lock_state, part.lock_motion) if o is not None]
            for obj in objects:
                self._own["foot_lock"].remove(obj)
            part.lock_state = part.lock_motion = None
            try:
                if agents:
                    state = self.ctx.buffer(reserve=size)
                    self._own["foot_lock"].append(state)
                    state.clear()
                    if was is not None:
                        self.ctx.copy_buffer(state, was, size=min(size, was.size))
                    part.lock_motion = self.ctx.buffer(reserve=agents * 16)
                    self._own["foot_lock"].append(part.lock_motion)
                    part.lock_state = state
            finally:
                for obj in objects:
                    obj.release()

    def _allocate(self, counts: tuple[int, ...], keep: bool = False) -> None:
        layout = self._layout(counts)
        rows = layout.rows
        limit, max_layers = palette_limits(self.ctx)
        layer_rows = max(1, min(rows, limit))
        slot_layers = max(1, math.ceil(rows / layer_rows))
        layers = slot_layers * self.history
        width = layout.width
        agents = layout.agents
        if layers > max_layers or layers * layer_rows > MAX_PALETTE_ROWS:
            raise ProcessorError(f"{agents:,} agents with a palette history of {self.history} need {layers} palette layers of "
                                 f"{layer_rows:,} rows, more than this GPU's {max_layers} layers or the {MAX_PALETTE_ROWS:,} rows a texel code addresses")
        # The palettes kept across (`keep`, with something written and agents on both sides): the old
        # planes stay alive until they are copied; the ring's position (runs) carries over.
        old, old_objects = None, []  # (planes, their layout, layer rows and layers a slot), and what releases them
        if keep and self.planes and self.runs and agents:
            old = (self.planes, self.layout, self.layer_rows, self.slot_layers)
            old_objects, self._own["palette"] = self._own["palette"], []
            self.planes = ()
        self._drop_palette()
        self.layout, self.agents = layout, agents
        runs, self.runs = self.runs, 0
        self.layer_rows, self.slot_layers = layer_rows, slot_layers
        if agents == 0:
            return  # no agents: no palette, no layer texture, no pass
        layer_rows_needed = math.ceil(agents / self.layer_agents_per_row)
        # (the layer texture and its pixel-unpack buffer, the same size)
        need = 3 * width * layer_rows * layers * 16 + 2 * self.layer_agents_per_row * self.layer_count * layer_rows_needed * 16
        if self.path == "fragment":
            need += 3 * width * layer_rows * slot_layers * 16  # (the locals pass's scratch)
        self.ctx.error  # clear an earlier error, so the check below sees these allocations'
        failure = None
        try:
            self.planes = tuple(self._array("palette", (width, layer_rows, layers)) for _ in range(3))
            self._make_layers(agents)
            # A layered framebuffer over the planes: it clears every layer at once (texels no run wrote
            # read as 0, not as whatever the memory held), and the fragment path renders through it.
            fb = self.ctx.framebuffer(color_attachments=list(self.planes))
            self._own["palette"].append(fb)
            if self.path == "fragment":  # the locals pass's scratch: one ring slot's shape (processor.frag.glsl)
                self._locals = tuple(self._array("locals", (width, layer_rows, slot_layers)) for _ in range(3))
                self._locals_framebuffer = self.ctx.framebuffer(color_attachments=list(self._locals))
                self._own["locals"].append(self._locals_framebuffer)
        except moderngl.Error as exc:
            failure = f"the palette for {agents:,} agents ({need:,} bytes) could not be made: {exc}"
        if failure is None and self.ctx.error == "GL_OUT_OF_MEMORY":
            failure = f"the GPU ran out of memory for the palette of {agents:,} agents: {need:,} bytes were needed"
        if failure is not None:
            self._drop_palette()
            self.layout, self.agents = self._layout([0] * len(self.parts)), 0
            for obj in old_objects:
                obj.release()
            raise ProcessorError(failure)
        fb.clear(0.0, 0.0, 0.0, 0.0)
        if self.path == "fragment":
            self._framebuffer = fb
        self._update_quads()
        if old is not None:
            try:
                self._copy_palettes(*old)
                self.runs = runs
            finally:
                for obj in old_objects:
                    obj.release()

    def _copy_palettes(self, planes, layout: PaletteLayout, layer_rows: int, slot_layers: int) -> None:
        """Copy each character's kept rows of every ring slot of the old `planes` (laid out by `layout`, in
        layers of `layer_rows` rows, `slot_layers` a slot) into the same character's rows of the same
        slots of the new planes, on the GPU: each old plane into a pixel-pack buffer, then runs of rows
        that stay in one layer on both sides through a staging buffer into the new plane. An agent's
        texel within its character's block depends only on its place in that block, and a resize keeps
        each character's first agents, so a block's first rows move as they are."""
        width = planes[0].size[0]
        row_bytes = width * 16
        new_width = self.planes[0].size[0]
        blocks = []  # (old first row, new first row, rows) per character, in slot-relative rows
        for a, b in zip(layout.parts, self.layout.parts):
            rows = min(a.rows, b.rows)
            if rows:
                blocks.append((a.first_row, b.first_row, rows))
        if not blocks:
            return
        staging = self.ctx.buffer(reserve=max(min(max(r for *_, r in blocks), layer_rows, self.layer_rows) * row_bytes, 16))
        whole = self.ctx.buffer(reserve=planes[0].size[0] * planes[0].size[1] * planes[0].layers * 16)
        try:
            for old_plane, new_plane in zip(planes, self.planes):
                old_plane.read_into(whole)
                for slot in range(self.history):
                    for old_first, new_first, rows in blocks:
                        y = 0
                        while y < rows:
                            oy, ny = old_first + y, new_first + y
                            old_layer, old_row = slot * slot_layers + oy // layer_rows, oy % layer_rows
                            new_layer, new_row = slot * self.slot_layers + ny // self.layer_rows, ny % self.layer_rows
                            count = min(rows - y, layer_rows - old_row, self.layer_rows - new_row)
                            self.ctx.copy_buffer(staging, whole, size=count * row_bytes, read_offset=(old_layer * layer_rows + old_row) * row_bytes)
                            new_plane.write(staging, viewport=(0, new_row, new_layer, min(width, new_width), count, 1))
                            y += count
        finally:
            staging.release()
            whole.release()

    def _make_layers(self, agents: int) -> None:
        """The layer texture for `agents` agents (weight 0, the rest pose, until an upload) and its
        pixel-unpack buffer, in place of the ones before. The layers' whole rows go through that buffer:
        a buffer write ran at about 14 GB/s on the H200 host where a texture write from the array ran at
        2.6 (docs/BENCHMARKS.md, "The CPU side of the frame"), and the texture copy then runs on the GPU,
        in order after the last frame's pass."""
        self._release_group("layers")
        self.layers_texture = self._layer_unpack = None
        rows = math.ceil(agents / self.layer_agents_per_row)
        zeros = np.zeros((rows, self.layer_agents_per_row * self.layer_count, 4), np.float32)
        self.layers_texture = self._texture("layers", (self.layer_agents_per_row * self.layer_count, rows), 4, zeros, "f4")
        self._layer_unpack = self.ctx.buffer(reserve=zeros.nbytes)
        self._own["layers"].append(self._layer_unpack)

    def _drop_palette(self) -> None:
        """Release the palette planes, their framebuffer and the layer texture (the bakes' textures stay)."""
        self._release_group("palette")
        self._release_group("layers")
        self._release_group("locals")
        self.planes, self.layers_texture, self._framebuffer = (), None, None
        self._layer_unpack = None
        self._locals, self._locals_framebuffer = (), None

    def _array(self, group, size):
        tex = self.ctx.texture_array(size, 4, dtype="f4")
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._own[group].append(tex)
        return tex

    def _update_quads(self):
        """Fragment path: per character, the quads over its block's full palette rows and its partial last
        row, each cut at the layers of a ring slot, in one buffer (x, y in the layer's NDC, z the layer)."""
        if self.path != "fragment":
            return
        width, height = self.layout.width, self.layer_rows
        for part, block in zip(self.parts, self.layout.parts):
            full, partial = divmod(block.count, block.agents_per_row)
            spans = [(block.first_row, block.first_row + full, block.agents_per_row * block.width)]  # slot rows [y0, y1), width
            if partial:
                spans.append((block.first_row + full, block.first_row + full + 1, partial * block.width))
            verts = []
            for y0, y1, x1 in spans:
                y = y0
                while y < y1:
                    layer, row = divmod(y, height)
                    rows = min(y1 - y, height - row)
                    a, b = -1.0, 2.0 * x1 / width - 1.0
                    c, d = 2.0 * row / height - 1.0, 2.0 * (row + rows) / height - 1.0
                    verts += [(a, c, layer), (b, c, layer), (b, d, layer), (a, c, layer), (b, d, layer), (a, d, layer)]
                    y += rows
            part.quad_vertices = len(verts)
            data = np.asarray(verts, dtype=np.float32).tobytes()
            if part.quad is None or part.quad.size < max(len(data), 1):
                if part.quad is not None:
                    for obj in (part.quad_vao, part.locals_vao, part.quad):
                        self._own["processor_quad"].remove(obj)
                        obj.release()
                part.quad = self.ctx.buffer(reserve=max(len(data), 18 * 4))
                part.quad_vao = self.ctx.vertex_array(part.program, [(part.quad, "3f", "in_position")])
                part.locals_vao = self.ctx.vertex_array(part.locals_program, [(part.quad, "3f", "in_position")])
                self._own["processor_quad"] += [part.quad_vao, part.locals_vao, part.quad]
            if verts:
                part.quad.write(data)

    # -- the pass

    def upload(self, layers, motion=None, dt: float = 0.0) -> None:
        """Validate and upload this frame's layers (N, L, 4), or a sequence of blocks of consecutive
        agents that together are N (the crowd's, then the player's: no copy to join them); N must equal
        the agent count, and each character's agents' clips and masks are its own bake's (a character's
        agents lie in one block). With the foot lock, also each agent's `motion` (N, 4): its ground step
        since the last run (x, z, metres, from float64 positions) and its front (x, z) times its scale,
        and the frame's simulated seconds `dt`."""
        blocks = [np.asarray(b) for b in layers] if isinstance(layers, (list, tuple)) else [np.asarray(layers)]
        if len(blocks) == 1 and len(self.parts) == 1:
            p = self.parts[0]
            blocks = [validate_layers(blocks[0], len(p.bake.clips), 0 if p.masks is None else p.masks.shape[0], self.layer_count)]
        else:
            if any(b.ndim != 3 for b in blocks):
                raise ProcessorError(f"layers must be (agents, {self.layer_count}, 4) arrays, got {[b.shape for b in blocks]}")
            blocks = [b if b.dtype == np.float32 and b.flags.c_contiguous else np.ascontiguousarray(b, np.float32) for b in blocks]
            starts = np.cumsum([0] + [len(b) for b in blocks])
            if starts[-1] != self.agents:
                raise ProcessorError(f"layers are for {int(starts[-1])} agents, the processor holds {self.agents}")
            for k, (p, part) in enumerate(zip(self.parts, self.layout.parts)):
                if not part.count:
                    continue
                b = int(np.searchsorted(starts, part.first_agent, side="right")) - 1
                if part.first_agent + part.count > starts[b + 1]:
                    raise ProcessorError(f"character {k}'s agents span two blocks of layers; a character's lie in one")
                rows = blocks[b][part.first_agent - starts[b]:part.first_agent - starts[b] + part.count]
                try:
                    validate_layers(rows, len(p.bake.clips), 0 if p.masks is None else p.masks.shape[0], self.layer_count)
                except FrameError as exc:
                    raise FrameError(f"character {k}: {exc}") from None
        if sum(len(b) for b in blocks) != self.agents:
            raise ProcessorError(f"layers are for {sum(len(b) for b in blocks)} agents, the processor holds {self.agents}")
        if self.legs is not None:
            m = check_motion(motion, self.agents)
            if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt >= 0):
                raise ProcessorError(f"the foot lock needs a frame time >= 0 seconds, got {dt!r}")
            self._lock_dt = float(dt)
            for p, block in zip(self.parts, self.layout.parts):
                if p.lock_motion is not None and block.count:
                    # A fresh store for each frame's motion: the runs still queued read the last one.
                    part_motion = m[block.first_agent:block.first_agent + block.count]
                    p.lock_motion.orphan(part_motion.nbytes)
                    p.lock_motion.write(part_motion)
        first = 0
        for block in blocks:
            self._write_layers(block, first)
            first += len(block)

    def _write_layers(self, a: np.ndarray, first: int) -> None:
        """Layers of agents first .. first + len(a) - 1 into the layers texture: a partial first row, whole
        texture rows straight from the array (no padded copy), then a partial last row."""
        per_row, n = self.layer_agents_per_row, len(a)
        k = self.layer_count
        done = 0
        head = min((-first) % per_row, n)
        if head:
            row, x = divmod(first, per_row)
            self.layers_texture.write(np.ascontiguousarray(a[:head]), viewport=(x * k, row, head * k, 1))
            done = head
        full = (n - done) // per_row
        if full:
            rows = a[done:done + full * per_row]
            unpack = self._layer_unpack
            unpack.orphan(unpack.size)  # fresh storage: the copy still queued from the last frame keeps its own
            unpack.write(rows)
            self.layers_texture.write(unpack, viewport=(0, (first + done) // per_row, per_row * k, full))
            done += full * per_row
        if done < n:
            self.layers_texture.write(np.ascontiguousarray(a[done:]), viewport=(0, (first + done) // per_row, (n - done) * k, 1))

    def run(self) -> bool:
        """Write every agent's palette row: one dispatch per character with agents (the fragment path: two
        draws, its locals pass and its compose pass, processor.frag.glsl). Returns
        False when nothing ran."""
        if self.agents == 0:
            return False
        self.layers_texture.use(3)
        slot = self.runs % self.history  # the ring slot this run writes
        if self.path == "compute":
            for unit, plane in enumerate(self.planes):
                plane.bind_to_image(unit, read=False, write=True)
            for part, block in zip(self.parts, self.layout.parts):
                if block.count:
                    self._draw_part(part, block, slot, part.program)
        else:
            self.ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND | moderngl.CULL_FACE)
            # First every joint's blended local into the scratch, then the chains composed into the slot.
            self._locals_framebuffer.viewport = (0, 0, self.layout.width, self.layer_rows)
            self._locals_framebuffer.use()
            for part, block in zip(self.parts, self.layout.parts):
                if block.count:
                    self._draw_part(part, block, slot, part.locals_program)
            self._framebuffer.viewport = (0, 0, self.layout.width, self.layer_rows)
            self._framebuffer.use()
            for unit, plane in zip(LOCALS_UNITS, self._locals):
                plane.use(unit)
            for part, block in zip(self.parts, self.layout.parts):
                if block.count:
                    self._draw_part(part, block, slot, part.program)
        if self.path == "compute":
            # Later passes read the palette through texelFetch (and the readback through pack buffers).
            # The foot lock's next run reads the state this one wrote.
            self.ctx.memory_barrier(moderngl.TEXTURE_FETCH_BARRIER_BIT | moderngl.PIXEL_BUFFER_BARRIER_BIT | moderngl.TEXTURE_UPDATE_BARRIER_BIT
                                    | moderngl.SHADER_STORAGE_BARRIER_BIT)
        self.runs += 1
        return True

    def _draw_part(self, part: _Part, block, slot: int, prog) -> None:
        """One character's dispatch (compute) or draw (fragment: `prog` is its locals pass or its compose
        pass) over its block of the ring slot `slot`."""
        for unit, name in enumerate(("u_anim", "u_parents", "u_clips")):
            part.textures[name].use(unit)
        for unit, name in ((4, "u_anim_scale"), (5, "u_masks"), (6, "u_keys"), (7, "u_tracks"), (8, "u_morph_tracks"), (9, "u_morph_clips"),
                           (10, "u_morph_variation"), (11, "u_morph_held")):
            if name in part.textures:
                part.textures[name].use(unit)
        for name, unit in (("u_anim", 0), ("u_parents", 1), ("u_clips", 2), ("u_layers", 3), ("u_anim_scale", 4), ("u_masks", 5),
                           ("u_keys", 6), ("u_tracks", 7), ("u_morph_tracks", 8), ("u_morph_clips", 9), ("u_morph_variation", 10),
                           ("u_morph_held", 11), *zip(("u_locals0", "u_locals1", "u_locals2"), LOCALS_UNITS)):
            self._set(prog, name, unit)
        for name, value in part.uniforms.items():
            self._set(prog, name, value)
        self._set(prog, "u_row_offset", slot * self.slot_rows() + block.first_row)
        # (The locals pass writes the scratch, one slot deep: its layers count from 0.)
        self._set(prog, "u_first_layer", 0 if prog is part.locals_program else slot * self.slot_layers)
        self._set(prog, "u_palette_rows", self.layer_rows)
        self._set(prog, "u_agents", block.count)
        self._set(prog, "u_first_agent", block.first_agent)
        self._set(prog, "u_first_row", block.first_row)
        self._set(prog, "u_agents_per_row", block.agents_per_row)
        if part.held is not None:
            if part.held_written is not part.held:  # (hold_morphs makes a new array: written once a change)
                part.textures["u_morph_held"].write(part.held.tobytes())
                part.held_written = part.held
            self._set(prog, "u_morph_held_agent", part.held_agent)
        if part.legs is not None:
            for name, data in part.leg_bytes.items():
                prog[name].write(data)
            part.lock_state.bind_to_storage_buffer(0)
            part.lock_motion.bind_to_storage_buffer(1)
            self._set(prog, "u_lock_decay", math.exp(-self._lock_dt / lock.RELEASE_S))
            self._set(prog, "u_step_advance", self._lock_dt / lock.STEP_S)
        if self.path == "compute":
            groups = math.ceil(block.count / (GROUP_SIZE // block.width))
            gx = min(groups, 32768)
            prog.run(gx, math.ceil(groups / gx), 1)
        else:
            (part.locals_vao if prog is part.locals_program else part.quad_vao).render(moderngl.TRIANGLES, vertices=part.quad_vertices)

    def process(self, layers, motion=None, dt: float = 0.0) -> bool:
        self.upload(layers, motion, dt)
        return self.run()

    def reset_lock(self) -> None:
        """Every leg free with nothing carried (a new crowd in the same slots)."""
        for part in self.parts:
            if part.lock_state is not None:
                part.lock_state.clear()

    def read_lock_state(self, character: int = 0) -> np.ndarray:
        """(N, legs, 4) float32 foot-lock state of one character's agents (synchronous: tests only): engaged
        legs (hold x, z, yaw, 1), free ones (the correction carried x, z, yaw, 0)."""
        part, block = self.parts[character], self.layout.parts[character]
        if part.lock_state is None:
            return np.zeros((0, 0 if part.legs is None else len(part.legs), 4), np.float32)
        return np.frombuffer(part.lock_state.read(), np.float32).reshape(block.count, len(part.legs), 4)

    def hold_morphs(self, character: int, weights, agent: int) -> None:
        """Hold morph weights of one character from the next run: `weights` (M,), a weight in [0, 1] per
        target held, -1 where the clips and variation decide; `agent` its agent's number among the
        character's, or crowd.anim.morph.ALL_HELD / NOT_HELD. A character without morph tracks: ProcessorError."""
        part = self.parts[character]
        if part.held is None:
            raise ProcessorError(f"character {character} moves no morph target in this scene")
        w = np.asarray(weights, np.float32)
        if w.shape != part.held.shape or not np.all(np.isfinite(w)) or np.any(w > 1.0):
            raise ProcessorError(f"held morph weights must be {len(part.held)} values of at most 1 (-1: not held), got {np.asarray(weights).tolist()}")
        held = np.where(w >= 0.0, w, -1.0).astype(np.float32)
        if int(agent) != part.held_agent or not np.array_equal(held, part.held):  # (the texture is written when they change)
            part.held, part.held_agent = held, int(agent)

    def set_clip_loop(self, clip: int, loop: bool, character: int = 0) -> None:
        """Loop a clip of a character's bake (its phase wraps) or play it once (its phase clamps): that
        clip table is rewritten."""
        part = self.parts[character]
        if not 0 <= clip < len(part.bake.clips):
            raise ProcessorError(f"no clip {clip}; the bake has {len(part.bake.clips)}")
        part.bake.clips[clip] = dataclasses.replace(part.bake.clips[clip], loop=bool(loop))
        part.textures["u_clips"].write(np.ascontiguousarray(part.bake.clip_table).tobytes())

    def bind_palette(self, first_unit: int, *programs) -> None:
        """Bind the three planes (every palette of the history; texel codes say which rows) and tell
        `programs` (those that read them through shaders/palette.glsl) how many rows a layer holds."""
        for i, plane in enumerate(self.planes):
            plane.use(first_unit + i)
        for prog in programs:
            if "u_palette_rows" in prog:
                prog["u_palette_rows"] = self.layer_rows

    def read_palette(self, age: int = 0) -> np.ndarray:
        """(N, J, 3, 4) float32 skinning matrix rows of the palette written `age` runs ago, read back
        synchronously (tests and stats only); J is the largest skeleton's, and a smaller character's
        agents have zeros past their own joints."""
        n = self.agents
        jmax = max(p.bake.joint_count for p in self.parts)
        if n == 0:
            return np.zeros((0, jmax, 3, 4), np.float32)
        first = self.row_offset(age) if self.runs else 0
        planes = self._read_planes()
        out = np.zeros((n, jmax, 3, 4), np.float32)
        for block in self.layout.parts:
            if not block.count:
                continue
            rows, k, jc, w = block.rows, block.agents_per_row, block.joints, block.width
            y0 = first + block.first_row
            for r, plane in enumerate(planes):
                out[block.first_agent:block.first_agent + block.count, :jc, r] = \
                    plane[y0:y0 + rows, :k * w].reshape(rows * k, w, 4)[:block.count, block.slots:]
        return out

    def read_morph_pairs(self, character: int = 0, age: int = 0) -> np.ndarray:
        """(N, MORPH_PAIRS, 2) float32 (target, weight) pairs of one character's agents, from the palette
        written `age` runs ago (synchronous: tests only); (N, 0, 2) for a character without morphs."""
        block = self.layout.parts[character]
        if not block.morph or not block.count:
            return np.zeros((block.count, 0, 2), np.float32)
        first = self.row_offset(age) if self.runs else 0
        rows, k, w = block.rows, block.agents_per_row, block.width
        y0 = first + block.first_row
        texels = [plane[y0:y0 + rows, :k * w].reshape(rows * k, w, 4)[:block.count, block.slots - 1] for plane in self._read_planes()]
        return np.concatenate(texels, axis=1).reshape(block.count, MORPH_PAIRS, 2)

    def read_impostor_keys(self, character: int = 0, age: int = 0) -> np.ndarray:
        """(N, 4) float32 impostor keys of one character's agents (clip, phase of the heaviest layer, 0, 0),
        from the palette written `age` runs ago (synchronous: tests only); (N, 0) without keys."""
        block = self.layout.parts[character]
        if not block.key or not block.count:
            return np.zeros((block.count, 0), np.float32)
        first = self.row_offset(age) if self.runs else 0
        rows, k, w = block.rows, block.agents_per_row, block.width
        y0 = first + block.first_row
        return self._read_planes()[0][y0:y0 + rows, :k * w].reshape(rows * k, w, 4)[:block.count, 0].copy()

    def _read_planes(self) -> list[np.ndarray]:
        """The three planes, every palette of the history, as (palette rows, width, 4) float32 (synchronous)."""
        return [np.frombuffer(p.read(), np.float32).reshape(p.layers * p.height, p.width, 4) for p in self.planes]

    def read_rows(self, agents: np.ndarray, joint, row_offsets: np.ndarray) -> np.ndarray:
        """(K, 3, 4) float32 skinning matrix rows of one joint (or one per agent) of some agents, each from
        the palette starting at its row offset (synchronous: tests and stats only)."""
        x, y = self.layout.texel(agents, joint, row_offsets)
        return np.stack([plane[y, x] for plane in self._read_planes()], axis=1)

    def nan_rows(self) -> int:
        """Agents whose palette row holds NaN or Inf (each character's own joints)."""
        pal = self.read_palette()
        if not len(pal):
            return 0
        bad = 0
        for block in self.layout.parts:
            rows = pal[block.first_agent:block.first_agent + block.count, :block.joints]
            bad += int(np.count_nonzero(~np.all(np.isfinite(rows), axis=(1, 2, 3))))
        return bad

    def gpu_bytes(self) -> dict[str, int]:
        return {group: gpu_bytes(objs) for group, objs in self._own.items()}

    def release(self) -> None:
        for group in list(self._own):
            self._release_group(group)
        self.planes, self.layers_texture, self._framebuffer = (), None, None
        self._layer_unpack, self._locals, self._locals_framebuffer = None, (), None
        for part in self.parts:
            part.lock_state = part.lock_motion = part.quad = part.quad_vao = part.locals_vao = None
        for program in self._programs.values():
            program.release()
        self._programs = {}
