"""Bake stage: clips → the AnimationTexture of local joint transforms as dual quaternions.

Contract: ``bake(skeleton, clips, fps=30, precision="f32")`` → ``AnimationBake``; ``fps`` may also be
``"source"``: each clip at its own key rate.

Layout of ``texels`` (rows, 2 * J, 4), one texture row per baked frame:
- row 0 holds each joint's inverse bind transform;
- each clip owns ``frame_count`` consecutive rows from ``first_row``, sampled at ``fps`` (the clip's
  duration divided into whole intervals: the nearest whole number when within 1e-5 of it, else the
  next, so the actual rate is at least the asked one and frames stay on evenly spaced source keys);
- texel 2j is joint j's real part (x, y, z, w) and texel 2j+1 its dual part;
- looping clips store a closing frame equal to their first pose, so frame i and i+1 always exist and
  the shader never wraps inside the texture: ``f = phase * (frame_count - 1)``, lerp frames floor(f) and
  floor(f) + 1, the same for looping and one-shot clips;
- keys are sign-aligned along each joint's track, closing frame included, so neighbours lerp blindly.
  (A joint that spins a full turn over a loop closes on -q: the extra frame makes that work too.)
- the last row (``rest_row``) holds the skeleton's rest pose as local DQs: the processor's fallback for
  a joint whose layer weights add up to about 0 (ozz-animation's blending job does the same).

Dual quaternions carry no scale. A character with joint scale (static or animated, such as
Quaternius' hedgehog) gets ``scale``: (rows, J) uniform scale per joint and frame (the geometric mean of
its three), which runs down the chains as glTF's does; characters without it get ``scale = None``, and
no scale texture exists. Non-uniform scale sits only where it cannot make skew: ``residual`` (rows, J, 3,
float32, or None where every joint's scale is uniform) is each joint's scale over that mean, applied to
its own skinning matrix only, so a leaf is drawn exactly and a joint with children exactly on its own
vertices, its children taking its uniform part; the bake names each such joint with how far (mm) its
descendants are from glTF's pose, measured over the baked frames.

Compressed: with precision "compressed" the clips' keys are quantised per track to the error bound
``bound_mm`` (crowd.anim.compress says how): ``packed`` holds what the GPU decodes, ``texels`` the
float64 decode of the same keys (the processor's twin reads it; only its rows 0 and ``rest_row`` are
uploaded), and ``compression`` reports the bytes, the ratio to the f32 bake and the largest key error.
Joint scale, where a character has it, stays an f32 texture.

Storage error: every bake measures what its storage (f16 or f32) does to the keys it stores
(``storage_error``: each joint skinned by the rounded keys against the float64 keys, at every stored
frame) and warns where that exceeds STORAGE_WARN_M (1 mm), naming the joint, clip and frame, with what
f32 would give. A warning, not a refusal: see the comment where it is raised.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..errors import CrowdError
from . import reference
from .compress import MAX_BITS, CompressedKeys, compress
from .. import transforms as tf
from ..asset.model import Clip, ModelError, Skeleton
from ..progress import Report, steps
from ..settings import DEFAULTS, SETTINGS, SOURCE_RATE

if TYPE_CHECKING:
    from .morph import MorphBake

PRECISIONS = {"f32": np.float32, "f16": np.float16}  # texture storage; "compressed" stores crowd.anim.compress's words
COMPRESSED = "compressed"
DEFAULT_BOUND_MM = DEFAULTS["compression_bound_mm"]
# The default rate, chosen by `crowd-bench error` (docs/BENCHMARKS.md) with the processor's default
# interpolation: the cheapest configuration that keeps the built-in zombie within 1 mm. Its clips have
# 30 keys per second; at 15 fps the attack swing is 97 mm off.
DEFAULT_FPS = DEFAULTS["bake_fps"]
MAX_ROWS = 16384  # GL_MAX_TEXTURE_SIZE guaranteed by every GL 4.x driver we target
# Joint scale within this of 1 is treated as 1 (exporters leave 0.99996 and the like); at 1 m from the
# joint that is 0.1 mm. Anything dropped this way is reported in the bake's warnings.
SCALE_EPS = 1e-4
# Storage rounding the bake reports: the project's accuracy target (docs/BENCHMARKS.md). Measured on every
# bake (a few milliseconds: one pass over the stored rows), see storage_error.
STORAGE_WARN_M = 1e-3


class BakeError(CrowdError, ValueError):
    """Bad bake input; the message is one line."""


@dataclass(frozen=True)
class ClipInfo:
    name: str
    first_row: int
    frame_count: int  # keys stored, closing key included (>= 2)
    fps: float  # actual key rate: (frame_count - 1) / duration
    loop: bool
    duration: float


@dataclass
class AnimationBake:
    joint_names: tuple[str, ...]
    parents: np.ndarray  # int32 (J,): the hierarchy texture
    texels: np.ndarray  # (rows, 2J, 4) float32 or float16
    scale: np.ndarray | None  # (rows, J) same dtype, or None when every joint keeps scale 1
    clips: list[ClipInfo]
    fps: float | str  # the asked rate, or SOURCE_RATE (each ClipInfo has the actual rate)
    precision: str
    warnings: list[str] = field(default_factory=list)
    # precision "compressed": the packed keys the GPU decodes; `texels` then holds their float64 decode
    # (the processor's twin reads it) and only its rows 0 and rest_row reach the GPU.
    packed: CompressedKeys | None = None
    bound_mm: float = DEFAULT_BOUND_MM  # the compression bound asked (kept for a later re-bake; used when compressed)
    # The character's morph weight tracks for these clips (crowd.anim.morph), or None where the scene
    # moves no morph target: then the processor and the draw have no morph code at all.
    morphs: "MorphBake | None" = None
    residual: np.ndarray | None = None  # (rows, J, 3) float32: non-uniform scale over `scale`, own matrix only; None: none

    @property
    def joint_count(self) -> int:
        return len(self.joint_names)

    @property
    def rows(self) -> int:
        return self.texels.shape[0]

    @property
    def rest_row(self) -> int:
        return self.texels.shape[0] - 1

    @property
    def clip_table(self) -> np.ndarray:
        """float32 (C, 4): first row, frame count, fps, loop flag, as the processor reads it."""
        return np.array([[c.first_row, c.frame_count, c.fps, float(c.loop)] for c in self.clips], dtype=np.float32).reshape(-1, 4)

    @property
    def gpu_texels(self) -> np.ndarray:
        """The DQ texture's rows as uploaded: every row, or for a compressed bake the inverse bind and the rest pose."""
        if self.packed is None:
            return self.texels
        return self.texels[[0, self.rest_row]].astype(np.float32)

    @property
    def nbytes(self) -> int:
        """Bytes of animation data on the GPU: DQ texture, packed keys if any, scale texture if any,
        hierarchy, clip table."""
        packed = 0 if self.packed is None else self.packed.nbytes
        scale = (0 if self.scale is None else self.scale.nbytes) + (0 if self.residual is None else self.residual.nbytes)
        return int(self.gpu_texels.nbytes + packed + scale + self.parents.astype(np.int32).nbytes + self.clip_table.nbytes)

    @property
    def f32_nbytes(self) -> int:
        """What the same bake takes in f32: the compression ratio's denominator."""
        scale = (0 if self.scale is None else self.scale.size * 4) + (0 if self.residual is None else self.residual.size * 4)
        return int(self.texels.size * 4 + scale + self.parents.astype(np.int32).nbytes + self.clip_table.nbytes)

    @property
    def compression(self) -> dict | None:
        """A compressed bake's bound, bytes, ratio to f32 and largest key error; None for f32 and f16."""
        k = self.packed
        if k is None:
            return None
        clip, key, joint = k.worst
        worst = f"clip {self.clips[clip].name!r}, frame {key}, joint {self.joint_names[joint]!r}" if self.clips else None
        return {"bound_mm": k.bound_m * 1e3, "max_key_error_mm": k.max_error_m * 1e3, "bytes": self.nbytes, "f32_bytes": self.f32_nbytes,
                "ratio": self.f32_nbytes / self.nbytes, "worst": worst,
                "mean_rotation_bits": float(k.rotation_bits.mean()) if k.rotation_bits.size else 0.0,
                "mean_translation_bits": float(k.translation_bits.mean()) if k.translation_bits.size else 0.0}

    def clip_index(self, name: str) -> int:
        for i, c in enumerate(self.clips):
            if c.name == name:
                return i
        raise BakeError(f"clip {name!r} was not baked; baked clips are {', '.join(c.name for c in self.clips)}")

    # -- A float64 model of what the processor does with this data (used by tests and error reports).

    def frame_position(self, clip: int, phases) -> tuple[np.ndarray, np.ndarray]:
        """Row index i0 and lerp factor for each phase, exactly as the shaders compute them."""
        info = self.clips[clip]
        p = np.asarray(phases, dtype=np.float64)
        p = np.mod(p, 1.0) if info.loop else np.clip(p, 0.0, 1.0)
        f = p * (info.frame_count - 1)
        i0 = np.clip(np.floor(f), 0, info.frame_count - 2).astype(np.int64)
        return info.first_row + i0, f - i0

    def sample_local(self, clip: int, phases):
        """Lerped, normalised local (real, dual, scale) per joint: (P, J, 4), (P, J, 4), (P, J)."""
        row, u = self.frame_position(clip, phases)
        t = self.texels.astype(np.float64)
        a, b = t[row], t[row + 1]
        lerp = a + (b - a) * u[:, None, None]
        real, dual = tf.dq_normalize(lerp[:, 0::2], lerp[:, 1::2])
        if self.scale is None:
            scale = np.ones(real.shape[:2])
        else:
            s = self.scale.astype(np.float64)
            scale = s[row] + (s[row + 1] - s[row]) * u[:, None]
        return real, dual, scale

    def sample_residual(self, clip: int, phases) -> np.ndarray:
        """Each joint's non-uniform scale over its uniform one, lerped as the processor lerps it: (P, J, 3)."""
        row, u = self.frame_position(clip, phases)
        if self.residual is None:
            return np.ones((len(row), self.joint_count, 3))
        r = self.residual.astype(np.float64)
        return r[row] + (r[row + 1] - r[row]) * u[:, None, None]

    def inverse_bind(self) -> np.ndarray:
        t = self.texels[0].astype(np.float64)
        s = None if self.scale is None else self.scale[0].astype(np.float64)
        return tf.dq_to_mat4(t[0::2], t[1::2], s)

    def skinning_matrices(self, clip: int, phases) -> np.ndarray:
        real, dual, scale = self.sample_local(clip, phases)
        local = tf.dq_to_mat4(real, dual, scale)
        glob = np.empty_like(local)
        for j, p in enumerate(self.parents):
            glob[:, j] = local[:, j] if p < 0 else glob[:, p] @ local[:, j]
        if self.residual is not None:  # (each joint's own matrix only)
            glob[..., :3, :3] = glob[..., :3, :3] * self.sample_residual(clip, phases)[..., None, :]
        return glob @ self.inverse_bind()[None]


def _uniform_scale(s: np.ndarray, where: str, warnings: list[str]) -> np.ndarray:
    """(…, 3) scale → (…,) uniform scale; non-uniform scale becomes its geometric mean, with a warning
    (the inverse binds: a skin bound through a non-uniform scale)."""
    mean = np.cbrt(np.prod(s, axis=-1))
    spread = float(np.max(np.abs(s - mean[..., None]))) if s.size else 0.0
    if spread > 1e-4:
        warnings.append(f"{where}: non-uniform scale (spread {spread:.3g}) approximated by its geometric mean")
    return mean


def _split_scale(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(…, 3) scale → (its geometric mean (…,), which runs down the chain; the rest (…, 3), own matrix only)."""
    s = np.asarray(s, np.float64)
    mean = np.cbrt(np.prod(s, axis=-1))
    return mean, s / np.where(mean == 0.0, 1.0, mean)[..., None]


def uneven_joints(residual: np.ndarray) -> np.ndarray:
    """The joints (indices) whose scale is non-uniform, beyond SCALE_EPS, in some row of `residual` (rows, J, 3)."""
    return np.flatnonzero(np.abs(np.asarray(residual, np.float64) - 1.0).max(axis=(0, 2)) > SCALE_EPS)


def _inner_residual_warnings(skeleton: Skeleton, poses: list, names: list[str], residual: np.ndarray, warnings: list[str]) -> None:
    """One line per joint with children whose scale is non-uniform: how far its descendants are from
    glTF's pose (their world positions with the full scale, skew and all, against the uniform part), the
    worst over the baked frames of every clip."""
    parents = np.asarray(skeleton.parents)
    has_children = np.zeros(len(parents), bool)
    has_children[parents[parents >= 0]] = True
    uneven = uneven_joints(residual)
    uneven = uneven[has_children[uneven]]
    if not uneven.size:
        return
    below = {j: [k for k in range(len(parents)) if _is_below(parents, k, j)] for j in uneven}
    worst = {j: (0.0, "") for j in uneven}
    for pose, name in zip(poses, names):
        truth = reference.global_matrices(skeleton, pose)[..., :3, 3]
        mean, _ = _split_scale(pose.scale)
        drawn = reference.global_matrices(skeleton, type(pose)(pose.translation, pose.rotation, np.repeat(mean[..., None], 3, -1)))[..., :3, 3]
        gap = np.linalg.norm(truth - drawn, axis=-1)  # (P, J)
        for j in uneven:
            if below[j]:
                e = float(gap[:, below[j]].max())
                if e > worst[j][0]:
                    worst[j] = (e, name)
    for j in uneven:
        e, name = worst[j]
        warnings.append(f"joint {skeleton.names[j]!r}: non-uniform scale on a joint with children: its own vertices are drawn with it, "
                        f"its children with its uniform part, up to {_length(e)} from glTF's pose ({name or 'its rest'})")


def _is_below(parents: np.ndarray, k: int, j: int) -> bool:
    p = int(parents[k])
    while p >= 0:
        if p == j:
            return True
        p = int(parents[p])
    return False


def _intervals(exact: float) -> int:
    """Whole key intervals for a clip of `exact` intervals at the asked rate. glTF stores key times as
    float32, so a 1.2 s clip lasts 1.2000000477 s: a plain ceil would bake 73 intervals at 60 fps
    instead of 72, and the bake's keys would drift off the source keys (issue 7 measured 21 mm)."""
    nearest = round(exact)
    if abs(exact - nearest) <= 1e-5 * max(1.0, exact):
        return max(1, int(nearest))
    return max(1, math.ceil(exact))


def _source_intervals(clip: Clip) -> int:
    """Intervals that put the bake's frames on the clip's own keys: the clip's duration over the
    shortest median key interval of its channels (exact for evenly keyed clips)."""
    steps = [float(np.median(np.diff(c.times))) for c in clip.channels if c.times.shape[0] > 1]
    steps = [h for h in steps if h > 0]
    if not steps or clip.duration <= 0:
        return 1
    return _intervals(clip.duration / min(steps))


def bake(skeleton: Skeleton, clips: list[Clip], fps: float | str = DEFAULT_FPS, precision: str = "f32", max_rows: int = MAX_ROWS,
         bound_mm: float = DEFAULT_BOUND_MM, report: Report | None = None) -> AnimationBake:
    """Bake the given clips (only those: pass the scene's clips, not every clip of the file). With
    precision "compressed", `bound_mm` is the largest error the compression may add at a key. Progress
    shows on a terminal, and goes to `report` (done, total, what) where given (crowd.progress)."""
    skeleton.validate()
    SETTINGS["bake_fps"].check(fps, BakeError)
    SETTINGS["precision"].check(precision, BakeError)
    bound_mm = SETTINGS["compression_bound_mm"].check(bound_mm, BakeError)
    names = [c.name for c in clips]
    if len(set(names)) != len(names):
        raise BakeError("the same clip is listed twice")
    for c in clips:
        try:
            c.validate(skeleton)
        except ModelError as exc:
            raise BakeError(str(exc)) from None
    warnings: list[str] = []
    jc = skeleton.joint_count

    # Row 0: inverse bind pose.
    t, q, s, shear = tf.mat4_decompose(skeleton.inverse_bind)
    if float(np.max(shear)) > 1e-4:
        raise BakeError(f"inverse bind matrices have shear {float(np.max(shear)):.3g}; a dual quaternion cannot hold it")
    if np.any(np.linalg.det(skeleton.inverse_bind[:, :3, :3]) <= 0):
        raise BakeError("an inverse bind matrix mirrors; a dual quaternion cannot hold it")
    real_rows = [q[None]]
    dual_rows = [tf.dq_from_rt(q, t)[1][None]]
    scale_rows = [_uniform_scale(s, "inverse bind", warnings)[None]]
    residual_rows = [np.ones((1, jc, 3))]
    poses, pose_names = [], []

    # How many rows the clips need, counted before any is sampled: a long clip at a high rate is
    # refused in a moment instead of after sampling hundreds of megabytes of poses.
    intervals = [_source_intervals(clip) if fps == SOURCE_RATE else _intervals(clip.duration * fps) for clip in clips]
    needed = 1 + sum(n + 1 for n in intervals) + 1  # inverse bind, the clips, the rest pose
    if needed > max_rows:
        raise BakeError(f"{needed} frames do not fit a {max_rows}-row texture: bake fewer clips or at a lower rate than {fps} fps")
    infos = []
    clip_keys = []  # per clip (rotation, translation, scale) float64: the compressor's input
    row = 1
    for clip, n in steps(list(zip(clips, intervals)), desc="baking clips", unit="clip", report=report):
        phases = np.arange(n + 1, dtype=np.float64) / n
        if clip.loop:
            phases[-1] = 0.0  # the closing frame repeats the first pose (then aligned to its predecessor)
        pose = reference.sample_clip(skeleton, clip, phases)
        qr = tf.align_quat_track(pose.rotation, axis=0)
        _, qd = tf.dq_from_rt(qr, pose.translation)
        real_rows.append(qr)
        dual_rows.append(qd)
        mean, rest_of = _split_scale(pose.scale)
        scale_rows.append(mean)
        residual_rows.append(rest_of)
        poses.append(pose)
        pose_names.append(f"clip {clip.name!r}")
        clip_keys.append((qr, pose.translation, scale_rows[-1]))
        actual = n / clip.duration if clip.duration > 0 else (1.0 if fps == SOURCE_RATE else float(fps))
        infos.append(ClipInfo(clip.name, row, n + 1, actual, clip.loop, clip.duration))
        row += n + 1
    rest_q = skeleton.rest_rotation
    real_rows.append(rest_q[None])
    dual_rows.append(tf.dq_from_rt(rest_q, skeleton.rest_translation)[1][None])
    mean, rest_of = _split_scale(skeleton.rest_scale)
    scale_rows.append(mean[None])
    residual_rows.append(rest_of[None])
    row += 1
    if 2 * jc > max_rows:
        raise BakeError(f"{jc} joints need {2 * jc} texels per row, more than {max_rows}")

    real = np.concatenate(real_rows)
    dual = np.concatenate(dual_rows)
    texels = np.empty((row, 2 * jc, 4), dtype=np.float64)
    texels[:, 0::2] = real
    texels[:, 1::2] = dual
    scale = np.concatenate(scale_rows)
    dtype = PRECISIONS.get(precision, np.float32)
    if not np.all(np.isfinite(texels)) or not np.all(np.isfinite(scale)):
        raise BakeError("baked transforms hold NaN or Inf")
    if precision == "f16" and (np.max(np.abs(texels)) > 60000.0 or np.max(np.abs(scale)) > 60000.0):
        raise BakeError("values exceed the half-float range; bake with precision f32")
    deviation = float(np.max(np.abs(scale - 1.0)))
    needs_scale = deviation > SCALE_EPS
    residual = np.concatenate(residual_rows)
    if not np.all(np.isfinite(residual)):
        raise BakeError("baked joint scales hold NaN or Inf")
    residual[:, np.abs(residual - 1.0).max(axis=(0, 2)) <= SCALE_EPS] = 1.0  # (uniform to within SCALE_EPS: uniform, as the GPU skips it)
    stored_residual = residual.astype(np.float32) if float(np.max(np.abs(residual - 1.0))) > SCALE_EPS else None
    if stored_residual is not None:
        _inner_residual_warnings(skeleton, poses, pose_names, residual, warnings)
    if 1e-6 < deviation <= SCALE_EPS:
        warnings.append(f"joint scale deviates from 1 by at most {deviation:.2g}; treated as 1 (no scale texture)")
    if precision == COMPRESSED:
        return dataclasses.replace(_compressed(skeleton, texels, scale if needs_scale else None, clip_keys, infos, fps, bound_mm, warnings, report),
                                   residual=stored_residual)
    stored_scale = scale.astype(dtype) if needs_scale else None
    # Warn, not refuse: f16 is a deliberate trade of accuracy for half the bytes, and its floor on a
    # human-sized character is about the 1 mm target itself (the built-in zombie's f16 keys are 1.03 mm
    # off): a refusal would take f16 away from the very characters it is for. Where the error is large
    # (a joint scaled 1e4 times), the warning says how large, where, and what f32 would give; the demo
    # prints it and the stats JSON carries it, so it is never silent.
    error, row_at, joint_at = storage_error(texels, scale if needs_scale else None, texels.astype(dtype), stored_scale, skeleton.parents)
    if error > STORAGE_WARN_M:
        line = (f"{precision} storage moves joint {skeleton.names[joint_at]!r} {_length(error)} from its float64 key "
                f"({_row_name(infos, row_at)}), more than {STORAGE_WARN_M * 1e3:g} mm")
        if precision != "f32":
            f32_error = storage_error(texels, scale if needs_scale else None, texels.astype(np.float32),
                                      scale.astype(np.float32) if needs_scale else None, skeleton.parents)[0]
            line += f"; precision f32 keeps it within {_length(f32_error)}"
        warnings.append(line)
    return AnimationBake(
        joint_names=skeleton.names,
        parents=skeleton.parents.astype(np.int32).copy(),
        texels=texels.astype(dtype),
        scale=stored_scale,
        clips=infos,
        fps=fps if fps == SOURCE_RATE else float(fps),
        precision=precision,
        warnings=warnings,
        bound_mm=bound_mm,
        residual=stored_residual,
    )


def _compressed(skeleton: Skeleton, texels: np.ndarray, scale: np.ndarray | None, clip_keys, infos: list[ClipInfo], fps, bound_mm: float,
                warnings: list[str], report: Report | None = None) -> AnimationBake:
    """The compressed bake: the clips' keys packed within the bound (crowd.anim.compress); `texels`
    keeps rows 0 and the rest row as they are, and the clips' rows become the packed keys' float64 decode."""
    scale_of = [np.ones(k[0].shape[:2]) if scale is None else scale[i.first_row : i.first_row + i.frame_count] for k, i in zip(clip_keys, infos)]
    try:
        packed = compress(skeleton, [(q, t, s) for (q, t, _), s in zip(clip_keys, scale_of)], bound_mm * 1e-3, report)
    except ValueError as exc:  # more keys than the track headers address
        raise BakeError(str(exc)) from None
    decoded = texels.copy()
    for info, (q, t) in zip(infos, packed.decoded):
        real, dual = tf.dq_from_rt(q, t)
        decoded[info.first_row : info.first_row + info.frame_count, 0::2] = real
        decoded[info.first_row : info.first_row + info.frame_count, 1::2] = dual
    if packed.max_error_m > packed.bound_m:
        clip, key, joint = packed.worst
        warnings.append(f"compressed keys move joint {skeleton.names[joint]!r} {_length(packed.max_error_m)} (clip {infos[clip].name!r}, "
                        f"frame {key}), more than the bound of {bound_mm:g} mm: {MAX_BITS} bits a component do not reach it")
    return AnimationBake(joint_names=skeleton.names, parents=skeleton.parents.astype(np.int32).copy(), texels=decoded,
                         scale=None if scale is None else scale.astype(np.float32), clips=infos, fps=fps if fps == SOURCE_RATE else float(fps),
                         precision=COMPRESSED, warnings=warnings, packed=packed, bound_mm=bound_mm)


def _length(metres: float) -> str:
    return f"{metres:.3g} m" if metres >= 1.0 else f"{metres * 1e3:.3g} mm"


def _row_name(infos: list[ClipInfo], row: int) -> str:
    if row == 0:
        return "inverse bind"
    for info in infos:
        if info.first_row <= row < info.first_row + info.frame_count:
            return f"clip {info.name!r}, frame {row - info.first_row}"
    return "rest pose"


def _decode(texels: np.ndarray, scale: np.ndarray | None) -> np.ndarray:
    """(rows, J, 4, 4) float64 matrices of stored keys, decoded as the processor decodes them (the real
    part made unit first)."""
    t = np.asarray(texels, np.float64)
    return tf.dq_to_mat4(t[:, 0::2], t[:, 1::2], None if scale is None else np.asarray(scale, np.float64))


def _skinned_joints(local: np.ndarray, inverse_bind: np.ndarray, parents: np.ndarray, bind: np.ndarray) -> np.ndarray:
    """(rows, J, 3): each joint's bind position `bind` (J, 4) skinned by pose rows `local` and the
    inverse bind `inverse_bind` (J, 4, 4)."""
    glob = np.empty_like(local)
    for j, p in enumerate(parents):
        glob[:, j] = local[:, j] if p < 0 else glob[:, p] @ local[:, j]
    return np.einsum("rjab,jb->rja", (glob @ inverse_bind[None])[..., :3, :], bind)


def storage_error(texels: np.ndarray, scale: np.ndarray | None, stored: np.ndarray, stored_scale: np.ndarray | None,
                  parents: np.ndarray, chunk: int = 512) -> tuple[float, int, int]:
    """(metres, row, joint): the largest distance, over every stored pose row (the clips' frames and
    the rest row) and joint, between a joint skinned by the stored (rounded) keys and by the float64
    keys, the inverse bind of row 0 included. A key's rounding adds up through the hierarchy and is
    multiplied by the joint scales on the way: that is how f16 puts a joint scaled 1e4 times metres
    off, while it moves the zombie's joints 1 mm. Rows go `chunk` at a time (a 16,384-row bake of 256
    joints would otherwise hold half a gigabyte of matrices)."""
    exact_ib = _decode(texels[:1], None if scale is None else scale[:1])[0]
    stored_ib = _decode(stored[:1], None if stored_scale is None else stored_scale[:1])[0]
    bind = np.linalg.inv(exact_ib)[:, :, 3]
    worst, at = -1.0, (1, 0)
    for first in range(1, texels.shape[0], chunk):
        rows = slice(first, min(first + chunk, texels.shape[0]))
        exact = _skinned_joints(_decode(texels[rows], None if scale is None else scale[rows]), exact_ib, parents, bind)
        rounded = _skinned_joints(_decode(stored[rows], None if stored_scale is None else stored_scale[rows]), stored_ib, parents, bind)
        err = np.linalg.norm(rounded - exact, axis=-1)
        r, j = np.unravel_index(int(np.argmax(err)), err.shape)
        if err[r, j] > worst:
            worst, at = float(err[r, j]), (first + int(r), int(j))
    return max(worst, 0.0), at[0], at[1]


def joint_position_error(bake_: AnimationBake, skeleton: Skeleton, clip: Clip, phases) -> np.ndarray:
    """Per-phase max distance (metres) between baked and reference model-space joint positions."""
    ci = bake_.clip_index(clip.name)
    baked = bake_.skinning_matrices(ci, phases) @ np.linalg.inv(skeleton.inverse_bind)[None]
    ref = reference.global_matrices(skeleton, reference.sample_clip(skeleton, clip, phases))
    return np.max(np.linalg.norm(baked[..., :3, 3] - ref[..., :3, 3], axis=-1), axis=-1)
