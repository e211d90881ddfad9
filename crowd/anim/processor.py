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

Paths: "compute" (GL 4.3, one dispatch) and "fragment" (GL 3.3, one draw); "auto" takes compute where
the context has GL 4.3. Both run the same GLSL (shaders/processor_common.glsl).
"""

from __future__ import annotations

import dataclasses
import math

import moderngl
import numpy as np

from .. import transforms as tf
from ..frame import CLIP, MASK, MAX_LAYERS, PHASE, WEIGHT, validate_layers, validate_masks
from .bake import AnimationBake
from .compress import PER_KEY
from . import foot_lock as lock
from ..gl import GLStage, gpu_bytes, has_compute, load_shader
from ..settings import DEFAULTS, SETTINGS
from .reference import CANCELLED_NORM, REST_THRESHOLD, aligned_sign

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


def resolve_path(ctx: moderngl.Context, path: str) -> str:
    """The processor path "auto" takes on this context: compute where it has GL 4.3, else fragment."""
    return ("compute" if has_compute(ctx) else "fragment") if path == "auto" else path


def check_motion(motion, agents: int) -> np.ndarray:
    """The foot lock's per-agent motion (N, 4) float32: ground step x, z and front x, z times the scale,
    all finite, the front not 0."""
    if motion is None:
        raise ProcessorError("the foot lock needs each agent's motion (ground step x, z, front x, z times scale) with its layers")
    m = np.ascontiguousarray(motion, np.float32)
    if m.shape != (agents, 4):
        raise ProcessorError(f"agent motion must be ({agents}, 4) (ground step x, z, front x, z times scale), got {np.shape(motion)}")
    # Two reductions where every value is fine (min and max carry NaN and infinities); the row is found only for the message.
    if m.size and not (np.isfinite(m.min()) and np.isfinite(m.max())):
        bad = int(np.flatnonzero(~np.all(np.isfinite(m), axis=1))[0])
        raise ProcessorError(f"agent motion of agent {bad} is not finite: {m[bad].tolist()}")
    front = m[:, 2] * m[:, 2] + m[:, 3] * m[:, 3]
    if front.size and not front.min() > 1e-24:
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


class AnimationProcessor(GLStage):
    """Owns the bake's GPU textures, the layers texture and the palette planes, and releases them."""

    def __init__(self, ctx: moderngl.Context, bake: AnimationBake, layer_count: int = MAX_LAYERS, masks=None, path: str = "auto",
                 history: int = 1, interpolation: str = DEFAULT_INTERPOLATION, legs: lock.Legs | None = None):
        self._own: dict[str, list] = {"animation": [], "palette": [], "layers": [], "processor_quad": [], "foot_lock": []}
        self.program = None
        SETTINGS["processor"].check(path, ProcessorError)
        if not 1 <= layer_count <= MAX_LAYERS:
            raise ProcessorError(f"layer count must be 1 to {MAX_LAYERS}, got {layer_count}")
        jc = bake.joint_count
        if not 1 <= jc <= MAX_JOINTS:
            raise ProcessorError(f"the processor handles 1 to {MAX_JOINTS} joints, this skeleton has {jc}")
        if np.any(bake.parents >= np.arange(jc)):
            raise ProcessorError("the hierarchy must list parents before their children")
        path = resolve_path(ctx, path)
        if path == "compute" and not has_compute(ctx):
            raise ProcessorError(f"the compute path needs GL 4.3, this context has {ctx.version_code}")
        # The foot lock (crowd.anim.foot_lock): legs given and found, on the compute path, whose shared
        # memory holds an agent's locals between the blend and the composition.
        self.legs = legs if legs is not None and len(legs) else None
        if self.legs is not None and path != "compute":
            raise ProcessorError("the foot lock runs on the compute path (GL 4.3); the fragment path has no state to keep it in")
        self._lock_state = self._lock_motion = None
        self._lock_dt = 0.0  # the simulated seconds of the frame the last upload was for
        self.ctx = ctx
        self.bake = bake
        self.path = path
        self.layer_count = layer_count
        self.joint_count = jc
        self.masks = validate_masks(masks, jc)
        self.interpolation = check_interpolation(interpolation)
        self.agents_per_row = max(1, MAX_TEXTURE_WIDTH // max(jc, layer_count))
        self.agents_per_group = GROUP_SIZE // jc
        self.agents = 0
        self.history = _check_history(history)
        self.runs = 0  # runs since the palette was last (re)allocated: slots older than this hold nothing
        self.layer_rows = 1  # texture rows per layer of the planes
        self.slot_layers = 1  # layers one ring slot spans

        compressed = bake.packed is not None
        dtype = "f2" if bake.precision == "f16" else "f4"
        anim_rows = bake.gpu_texels
        self.anim_texture = self._texture("animation", (2 * jc, anim_rows.shape[0]), 4, anim_rows, dtype)
        self.scale_texture = None if bake.scale is None else self._texture("animation", (jc, bake.rows), 1, bake.scale, dtype)
        self.keys_texture = self.tracks_texture = None
        if compressed:
            words = bake.packed.word_texture
            self.keys_texture = self._texture("animation", (words.shape[1], words.shape[0]), 1, words, "u4")
            headers = bake.packed.header_texture
            self.tracks_texture = self._texture("animation", (4 * jc, headers.shape[0]), 4, headers, "u4")
        self.parents_texture = self._texture("animation", (jc, 1), 1, bake.parents.astype(np.int32), "i4")
        self.clips_texture = self._texture("animation", (len(bake.clips), 1), 4, bake.clip_table, "f4")
        self.masks_texture = None if self.masks is None else self._texture("animation", (jc, self.masks.shape[0]), 1, self.masks, "f4")
        defines = {"LAYERS": layer_count, "REST_THRESHOLD": f"{REST_THRESHOLD:.1e}", "CANCELLED_NORM": f"{CANCELLED_NORM:.1e}",
                   "MAX_JOINTS": MAX_JOINTS}
        if self.scale_texture is not None:
            defines["HAS_SCALE"] = 1
        if compressed:
            defines["COMPRESSED"] = 1
            defines["PER_KEY"] = f"{PER_KEY}u"
        if self.masks_texture is not None:
            defines["HAS_MASKS"] = 1
        if self.legs is not None:
            defines.update(FOOT_LOCK=1, LEG_COUNT=len(self.legs), CORRECTION_EPS=f"{lock.CORRECTION_EPS:.1e}",
                           **{name: repr(float(getattr(lock, name))) for name in ("CONTACT_M", "STEP_SHIFT_M", "STEP_TWIST_RAD", "HOLD_SHIFT_M",
                                                                                  "HOLD_TWIST_RAD", "STEP_LIFT_M", "RESET_M", "RESET_RAD",
                                                                                  "MIN_FORWARD_HORIZONTAL")})
        if interpolation != "dq_lerp":
            defines["INTERPOLATION_QT"] = 1
        if interpolation == "qt_cubic":
            defines["INTERPOLATION_CUBIC"] = 1
        if interpolation == "qt_corrected":
            defines["INTERPOLATION_CORRECTED"] = 1
            defines["SLERP_FIT_A"] = "vec3({:.12f}, {:.12f}, {:.12f})".format(*SLERP_FIT[:3])
            defines["SLERP_FIT_B"] = "vec3({:.12f}, {:.12f}, {:.12f})".format(*SLERP_FIT[3:])
        if path == "compute":
            self.program = ctx.compute_shader(load_shader("processor.comp.glsl", defines))
        else:
            self.program = ctx.program(vertex_shader=load_shader("processor.vert.glsl"), geometry_shader=load_shader("processor.geom.glsl"),
                                       fragment_shader=load_shader("processor.frag.glsl", defines))
        samplers = {"u_anim": 0, "u_parents": 1, "u_clips": 2, "u_layers": 3, "u_anim_scale": 4, "u_masks": 5, "u_keys": 6, "u_tracks": 7}
        for name, unit in samplers.items():
            if name in self.program:
                self.program[name] = unit
        self._set("u_joints", jc)
        self._set("u_agents_per_row", self.agents_per_row)
        self._set("u_agents_per_group", self.agents_per_group)
        self._set("u_rest_row", anim_rows.shape[0] - 1)
        self._set("u_rest_scale_row", bake.rest_row)
        if compressed:
            self._set("u_key_width", words.shape[1])
        if self.legs is not None:
            self.program["u_leg_joints"].write(np.ascontiguousarray(self.legs.joints, np.int32).tobytes())
            self.program["u_leg_toe"].write(np.ascontiguousarray(self.legs.toe, np.int32).tobytes())
            self.program["u_leg_forward"].write(np.ascontiguousarray(self.legs.forward, np.float32).tobytes())
            self.program["u_leg_lowest"].write(np.ascontiguousarray(self.legs.lowest, np.float32).tobytes())
        self._set("u_row_offset", 0)
        self.layers_texture = None
        self.planes: tuple = ()
        self._framebuffer = None
        self._quad = None
        self._quad_vao = None
        self._quad_vertices = 0

    # -- resources

    def _texture(self, group, size, components, data, dtype):
        tex = self.ctx.texture(size, components, None if data is None else np.ascontiguousarray(data).tobytes(), dtype=dtype)
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._own[group].append(tex)
        return tex

    def _set(self, name, value):
        if name in self.program:
            self.program[name] = value

    def _release_group(self, group):
        for obj in self._own[group]:
            obj.release()
        self._own[group] = []

    def palette_rows(self, agents: int | None = None) -> int:
        """Palette rows the agents fill (one ring slot's)."""
        n = self.agents if agents is None else agents
        return math.ceil(n / self.agents_per_row)

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
            self._allocate(self.agents)

    def resize(self, agents: int) -> None:
        """Make room for exactly `agents` agents; everything for agents no longer there is released. The
        agents kept keep their palette history: the same texture rows are kept as they are, and new
        planes get the kept palettes copied across on the GPU (so weapons stay in hand through it)."""
        if not isinstance(agents, (int, np.integer)) or agents < 0:
            raise ProcessorError(f"agent count must be a whole number >= 0, got {agents!r}")
        agents = int(agents)
        try:
            if self.palette_rows(agents) == self.palette_rows() and self.planes and agents:
                self.agents = agents  # the same texture rows: the agents kept keep their palette history
                self._update_quad()
                return
            self._allocate(agents, keep=True)
        finally:
            self._resize_lock(self.agents)

    def _resize_lock(self, agents: int) -> None:
        """The foot lock's state (a vec4 per agent and leg) and motion (a vec4 per agent) buffers, for
        `agents`: the agents kept keep their state, new ones start free with nothing carried."""
        if self.legs is None:
            return
        size = agents * len(self.legs) * 16
        if self._lock_state is not None and self._lock_state.size == size and agents:
            return
        old, old_objects = self._lock_state, self._own["foot_lock"]
        self._own["foot_lock"] = []
        self._lock_state = self._lock_motion = None
        try:
            if agents:
                state = self.ctx.buffer(reserve=size)
                self._own["foot_lock"].append(state)
                state.clear()
                if old is not None:
                    self.ctx.copy_buffer(state, old, size=min(size, old.size))
                self._lock_motion = self.ctx.buffer(reserve=agents * 16)
                self._own["foot_lock"].append(self._lock_motion)
                self._lock_state = state
        finally:
            for obj in old_objects:
                obj.release()

    def _allocate(self, agents: int, keep: bool = False) -> None:
        rows = self.palette_rows(agents)
        limit, max_layers = palette_limits(self.ctx)
        layer_rows = max(1, min(rows, limit))
        slot_layers = max(1, math.ceil(rows / layer_rows))
        layers = slot_layers * self.history
        width = self.agents_per_row * self.joint_count
        if layers > max_layers or layers * layer_rows > MAX_PALETTE_ROWS:
            raise ProcessorError(f"{agents:,} agents with a palette history of {self.history} need {layers} palette layers of "
                                 f"{layer_rows:,} rows, more than this GPU's {max_layers} layers or the {MAX_PALETTE_ROWS:,} rows a texel code addresses")
        # The palettes kept across (`keep`, with something written and agents on both sides): the old
        # planes stay alive until they are copied; the ring's position (runs) carries over.
        old, old_objects = None, []  # (planes, their layer rows and layers a slot, rows kept), and what releases them
        if keep and self.planes and self.runs and agents:
            old = (self.planes, self.layer_rows, self.slot_layers, min(self.palette_rows(), self.palette_rows(agents)))
            old_objects, self._own["palette"] = self._own["palette"], []
            self.planes = ()
        self._drop_palette()
        self.agents = agents
        runs, self.runs = self.runs, 0
        self.layer_rows, self.slot_layers = layer_rows, slot_layers
        if agents == 0:
            return  # no agents: no palette, no layer texture, no pass
        need = 3 * width * layer_rows * layers * 16 + width // self.joint_count * self.layer_count * rows * 16
        self.ctx.error  # clear an earlier error, so the check below sees these allocations'
        failure = None
        try:
            self.planes = tuple(self._array("palette", (width, layer_rows, layers)) for _ in range(3))
            zeros = np.zeros((rows, self.agents_per_row * self.layer_count, 4), np.float32)  # weight 0 (the rest pose) until an upload
            self.layers_texture = self._texture("layers", (self.agents_per_row * self.layer_count, rows), 4, zeros, "f4")
            # A layered framebuffer over the planes: it clears every layer at once (texels no run wrote
            # read as 0, not as whatever the memory held), and the fragment path renders through it.
            fb = self.ctx.framebuffer(color_attachments=list(self.planes))
            self._own["palette"].append(fb)
        except moderngl.Error as exc:
            failure = f"the palette for {agents:,} agents ({need:,} bytes) could not be made: {exc}"
        if failure is None and self.ctx.error == "GL_OUT_OF_MEMORY":
            failure = f"the GPU ran out of memory for the palette of {agents:,} agents: {need:,} bytes were needed"
        if failure is not None:
            self._drop_palette()
            self.agents = 0
            for obj in old_objects:
                obj.release()
            raise ProcessorError(failure)
        fb.clear(0.0, 0.0, 0.0, 0.0)
        if self.path == "fragment":
            self._framebuffer = fb
        self._update_quad()
        if old is not None:
            try:
                self._copy_palettes(*old)
                self.runs = runs
            finally:
                for obj in old_objects:
                    obj.release()

    def _copy_palettes(self, planes, layer_rows: int, slot_layers: int, rows: int) -> None:
        """Copy the first `rows` rows of every ring slot of the old `planes` (laid out in layers of
        `layer_rows` rows, `slot_layers` a slot) into the same rows of the same slots of the new
        planes, on the GPU: each old plane into a pixel-pack buffer, then runs of rows that stay in one
        layer on both sides through a staging buffer into the new plane. An agent's texel within its
        slot (palette_texel) does not depend on the crowd's size, so the rows move as they are."""
        width = planes[0].size[0]
        row_bytes = width * 16
        staging = self.ctx.buffer(reserve=max(min(rows, layer_rows, self.layer_rows) * row_bytes, 16))
        whole = self.ctx.buffer(reserve=planes[0].size[0] * planes[0].size[1] * planes[0].layers * 16)
        try:
            for old_plane, new_plane in zip(planes, self.planes):
                old_plane.read_into(whole)
                for slot in range(self.history):
                    y = 0
                    while y < rows:
                        old_layer, old_row = slot * slot_layers + y // layer_rows, y % layer_rows
                        new_layer, new_row = slot * self.slot_layers + y // self.layer_rows, y % self.layer_rows
                        count = min(rows - y, layer_rows - old_row, self.layer_rows - new_row)
                        self.ctx.copy_buffer(staging, whole, size=count * row_bytes, read_offset=(old_layer * layer_rows + old_row) * row_bytes)
                        new_plane.write(staging, viewport=(0, new_row, new_layer, width, count, 1))
                        y += count
        finally:
            staging.release()
            whole.release()

    def _drop_palette(self) -> None:
        """Release the palette planes, their framebuffer and the layer texture (the bake's textures stay)."""
        self._release_group("palette")
        self._release_group("layers")
        self.planes, self.layers_texture, self._framebuffer = (), None, None

    def _array(self, group, size):
        tex = self.ctx.texture_array(size, 4, dtype="f4")
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._own[group].append(tex)
        return tex

    def _update_quad(self):
        """Fragment path: per layer of a ring slot, the quad over its full palette rows, plus the
        partial last row of the last layer, in one buffer (x, y in the layer's NDC, z the layer)."""
        if self.path != "fragment":
            return
        width, height = self.agents_per_row * self.joint_count, self.layer_rows
        full, partial = divmod(self.agents, self.agents_per_row)
        rects = []  # (layer, x0, y0, x1, y1) in texels of that layer
        for layer in range(self.slot_layers):
            first = layer * height
            rows = min(full - first, height)
            if rows > 0:
                rects.append((layer, 0, 0, width, rows))
        if partial:
            layer, row = divmod(full, height)
            rects.append((layer, 0, row, partial * self.joint_count, row + 1))
        verts = []
        for layer, x0, y0, x1, y1 in rects:
            a, b = 2.0 * x0 / width - 1.0, 2.0 * x1 / width - 1.0
            c, d = 2.0 * y0 / height - 1.0, 2.0 * y1 / height - 1.0
            verts += [(a, c, layer), (b, c, layer), (b, d, layer), (a, c, layer), (b, d, layer), (a, d, layer)]
        self._quad_vertices = len(verts)
        data = np.asarray(verts, dtype=np.float32).tobytes()
        if self._quad is None or self._quad.size < max(len(data), 1):
            if self._quad is not None:
                self._own["processor_quad"] = []
                self._quad_vao.release()
                self._quad.release()
            self._quad = self.ctx.buffer(reserve=max(len(data), 18 * 4))
            self._quad_vao = self.ctx.vertex_array(self.program, [(self._quad, "3f", "in_position")])
            self._own["processor_quad"] += [self._quad_vao, self._quad]
        if verts:
            self._quad.write(data)

    # -- the pass

    def upload(self, layers, motion=None, dt: float = 0.0) -> None:
        """Validate and upload this frame's layers (N, L, 4); N must equal the agent count. With the foot
        lock, also each agent's `motion` (N, 4): its ground step since the last run (x, z, metres, from
        float64 positions) and its front (x, z) times its scale, and the frame's simulated seconds `dt`."""
        a = validate_layers(layers, len(self.bake.clips), 0 if self.masks is None else self.masks.shape[0], self.layer_count)
        if a.shape[0] != self.agents:
            raise ProcessorError(f"layers are for {a.shape[0]} agents, the processor holds {self.agents}")
        if self.legs is not None:
            m = check_motion(motion, self.agents)
            if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt >= 0):
                raise ProcessorError(f"the foot lock needs a frame time >= 0 seconds, got {dt!r}")
            self._lock_dt = float(dt)
            if self.agents:
                # A fresh store for each frame's motion: the runs still queued read the last one.
                self._lock_motion.orphan(m.nbytes)
                self._lock_motion.write(m)
        if self.agents == 0:
            return
        # Whole texture rows straight from the array (no padded copy), then the last, partial row.
        per_row, width = self.agents_per_row, self.agents_per_row * self.layer_count
        full = self.agents // per_row
        if full:
            self.layers_texture.write(a[: full * per_row], viewport=(0, 0, width, full))
        rest = self.agents - full * per_row
        if rest:
            last = np.zeros((per_row, self.layer_count, 4), np.float32)
            last[:rest] = a[full * per_row:]
            self.layers_texture.write(last, viewport=(0, full, width, 1))

    def run(self) -> bool:
        """Write every agent's palette row in one dispatch or one draw. Returns False when nothing ran."""
        if self.agents == 0:
            return False
        self.anim_texture.use(0)
        self.parents_texture.use(1)
        self.clips_texture.use(2)
        self.layers_texture.use(3)
        slot = self.runs % self.history  # the ring slot this run writes
        self._set("u_row_offset", slot * self.slot_rows())
        self._set("u_first_layer", slot * self.slot_layers)
        self._set("u_palette_rows", self.layer_rows)
        if self.scale_texture is not None:
            self.scale_texture.use(4)
        if self.masks_texture is not None:
            self.masks_texture.use(5)
        if self.keys_texture is not None:
            self.keys_texture.use(6)
            self.tracks_texture.use(7)
        if self.legs is not None:
            self._lock_state.bind_to_storage_buffer(0)
            self._lock_motion.bind_to_storage_buffer(1)
            self._set("u_lock_decay", math.exp(-self._lock_dt / lock.RELEASE_S))
            self._set("u_step_advance", self._lock_dt / lock.STEP_S)
        self._set("u_agents", self.agents)
        if self.path == "compute":
            for unit, plane in enumerate(self.planes):
                plane.bind_to_image(unit, read=False, write=True)
            groups = math.ceil(self.agents / self.agents_per_group)
            gx = min(groups, 32768)
            self.program.run(gx, math.ceil(groups / gx), 1)
            # Later passes read the palette through texelFetch (and the readback through pack buffers).
            # The foot lock's next run reads the state this one wrote.
            self.ctx.memory_barrier(moderngl.TEXTURE_FETCH_BARRIER_BIT | moderngl.PIXEL_BUFFER_BARRIER_BIT | moderngl.TEXTURE_UPDATE_BARRIER_BIT
                                    | moderngl.SHADER_STORAGE_BARRIER_BIT)
        else:
            self._framebuffer.viewport = (0, 0, self.agents_per_row * self.joint_count, self.layer_rows)
            self._framebuffer.use()
            self.ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND | moderngl.CULL_FACE)
            self._quad_vao.render(moderngl.TRIANGLES, vertices=self._quad_vertices)
        self.runs += 1
        return True

    def process(self, layers, motion=None, dt: float = 0.0) -> bool:
        self.upload(layers, motion, dt)
        return self.run()

    def reset_lock(self) -> None:
        """Every leg free with nothing carried (a new crowd in the same slots)."""
        if self._lock_state is not None:
            self._lock_state.clear()

    def read_lock_state(self) -> np.ndarray:
        """(N, legs, 4) float32 foot-lock state (synchronous: tests only): engaged legs (hold x, z, yaw, 1),
        free ones (the correction carried x, z, yaw, 0)."""
        if self._lock_state is None:
            return np.zeros((0, 0 if self.legs is None else len(self.legs), 4), np.float32)
        return np.frombuffer(self._lock_state.read(), np.float32).reshape(self.agents, len(self.legs), 4)

    def set_clip_loop(self, clip: int, loop: bool) -> None:
        """Loop a clip (its phase wraps) or play it once (its phase clamps): the clip table is rewritten."""
        if not 0 <= clip < len(self.bake.clips):
            raise ProcessorError(f"no clip {clip}; the bake has {len(self.bake.clips)}")
        self.bake.clips[clip] = dataclasses.replace(self.bake.clips[clip], loop=bool(loop))
        self.clips_texture.write(np.ascontiguousarray(self.bake.clip_table).tobytes())

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
        synchronously (tests and stats only)."""
        n, jc, k = self.agents, self.joint_count, self.agents_per_row
        if n == 0:
            return np.zeros((0, jc, 3, 4), np.float32)
        rows = self.palette_rows()
        first = self.row_offset(age) if self.runs else 0
        planes = [plane[first : first + rows].reshape(rows * k, jc, 4)[:n] for plane in self._read_planes()]
        return np.stack(planes, axis=2)

    def _read_planes(self) -> list[np.ndarray]:
        """The three planes, every palette of the history, as (palette rows, width, 4) float32 (synchronous)."""
        return [np.frombuffer(p.read(), np.float32).reshape(p.layers * p.height, p.width, 4) for p in self.planes]

    def read_rows(self, agents: np.ndarray, joint: int, row_offsets: np.ndarray) -> np.ndarray:
        """(K, 3, 4) float32 skinning matrix rows of one joint of some agents, each from the palette
        starting at its row offset (synchronous: tests and stats only)."""
        x, y = palette_texel(agents, joint, row_offsets, self.agents_per_row, self.joint_count)
        return np.stack([plane[y, x] for plane in self._read_planes()], axis=1)

    def nan_rows(self) -> int:
        """Agents whose palette row holds NaN or Inf."""
        pal = self.read_palette()
        return int(np.count_nonzero(~np.all(np.isfinite(pal), axis=(1, 2, 3)))) if len(pal) else 0

    def gpu_bytes(self) -> dict[str, int]:
        return {group: gpu_bytes(objs) for group, objs in self._own.items()}

    def release(self) -> None:
        for group in list(self._own):
            self._release_group(group)
        self.planes, self.layers_texture, self._framebuffer = (), None, None
        self._lock_state = self._lock_motion = None
        if self.program is not None:
            self.program.release()
            self.program = None
