"""Compressed keys: every (clip, joint) track quantised to its own range, to an error bound, for the GPU.

Contract: ``compress(skeleton, clips, bound_m)`` → ``CompressedKeys``, with ``clips`` one
``(rotation (F, J, 4) sign-aligned along each track, translation (F, J, 3), scale (F, J))`` float64 per
clip, its F keys the bake's frames (the closing frame of a loop included).

Format (what shaders/processor_common.glsl decodes under COMPRESSED; ``decode`` is its float64 twin):
- a track is one joint's rotation or translation in one clip: three components a key, each an unsigned
  integer of the track's own width b (0 to MAX_BITS bits) over the track's own range (ACL's range
  reduction): value = low + k * step, with low and step float32;
- a rotation keeps three of its four components; the fourth is rebuilt as sqrt(1 - |xyz|^2) >= 0
  (each key's sign is chosen so that it is positive: the decoder realigns neighbours, as blends do).
  Which one: the component whose smallest magnitude along the track is largest, for the whole track
  (ACL always drops w; this keeps the rebuild well conditioned for a joint held half a turn about x),
  unless even that one falls below PER_KEY_BELOW somewhere (a joint that spins through a half turn:
  every component passes near 0). Then each key drops its own largest component, which is at least
  1/2, and carries its index in 2 bits ahead of its components ("smallest three");
- b = 0 is a constant track: every key is `low` (the middle of the track's range);
- keys are packed back to back, 3b bits each (3b + 2 with their own index), from bit 0 of the track's
  first 32-bit word of ``words`` (tracks start on whole words; two zero words close the stream, so a
  decoder may always read three);
- ``tracks``: uint32 (C, J, 4, 4), four RGBA32UI texels per (clip, joint): (rotation low xyz, rotation
  meta), (rotation step xyz, translation meta), (translation low xyz, 0), (translation step xyz, 0),
  floats as their bits; meta = first word << 8 | dropped component << 5 | b, the dropped component
  PER_KEY where each key names its own.

Widths: ACL's search, per clip, to KEY_SHARE of the bound (below, why not all of it). First the
smallest width for every rotation and one for every translation that keep the clip within half of that
each and within it together; then each track in turn, from the leaves up, lowered as far as the clip
stays within it. The error is ACL's: the float64 shell error (crowd.anim.shell) of every joint at every
key, the decoded keys against the bake's own. A lowered track changes only its joint's subtree, so only
that is recomputed.

Keys are not dropped (ACL also removes keys that interpolation rebuilds within the bound): every frame
stays a key, so the decoder finds a key by its index, with no search.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import transforms as tf
from ..asset.model import Skeleton
from ..asset.pose import global_matrices
from ..progress import Report, steps
from .shell import shell_points

# Keys are kept within this share of the bound. A clip alone is measured as a whole, so its joints'
# errors may cancel along a chain (a parent's error undone by its child's); a blend mixes the errors of
# several clips' keys, which need not cancel: at the full bound, blends of the built-in zombie's clips
# reached 1.08 times it (0.538 mm of 0.5, 500 random blends); at 0.9, 0.79 times over 4,000 (0.394 mm).
KEY_SHARE = 0.9
MAX_BITS = 20  # a key's 3 x 20 + 2 bits fit the 64 a decoder takes from the three words it reads
PER_KEY = 4  # the dropped-component code of a track whose every key carries its own
PER_KEY_BELOW = 0.25  # the rebuilt component's magnitude below which a whole-track choice is refused
MAX_KEY_ROW = 4096  # the word texture's width at most: word i at (i % width, i / width)
TRACK_TEXELS = 4
STREAM_PAD_WORDS = 2


@dataclass
class CompressedKeys:
    words: np.ndarray  # uint32 (W,): the packed key bits, STREAM_PAD_WORDS zero words last
    tracks: np.ndarray  # uint32 (C, J, 4, 4): per (clip, joint) four RGBA32UI texels (module docstring)
    decoded: list[tuple[np.ndarray, np.ndarray]]  # per clip (rotation (F, J, 4) aligned, translation (F, J, 3)) float64
    bound_m: float
    max_error_m: float  # the largest shell error over every clip, key and joint
    worst: tuple[int, int, int]  # (clip, key, joint) where it is
    rotation_bits: np.ndarray  # int (C, J)
    translation_bits: np.ndarray  # int (C, J)

    @property
    def word_texture(self) -> np.ndarray:
        """uint32 (rows, width) the word texture holds: as few rows of at most MAX_KEY_ROW words as
        hold the words, as narrow as they allow (the last row padded with zeros)."""
        rows = -(-self.words.size // MAX_KEY_ROW)
        width = -(-self.words.size // rows)
        out = np.zeros(rows * width, np.uint32)
        out[: self.words.size] = self.words
        return out.reshape(rows, width)

    @property
    def header_texture(self) -> np.ndarray:
        """uint32 (clips, 4J, 4) the header texture holds: a bake of no clips still gets one (unread) row."""
        c, j = self.tracks.shape[:2]
        return self.tracks.reshape(c, 4 * j, 4) if c else np.zeros((1, 4 * j, 4), np.uint32)

    @property
    def nbytes(self) -> int:
        """Bytes on the GPU: the word texture and the header texture."""
        return int(self.word_texture.nbytes + self.header_texture.nbytes)


def _f32(x) -> np.ndarray:
    return np.asarray(x, np.float64).astype(np.float32).astype(np.float64)


def _range(values: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """float32-exact (low, step) of a track (F, 3) at `bits`: low + k * step, k in [0, 2^bits - 1], covers it."""
    lo, hi = values.min(axis=0), values.max(axis=0)
    if bits == 0:
        return _f32(0.5 * (lo + hi)), np.zeros(3)
    low = _f32(lo)
    step = _f32((hi - low) / ((1 << bits) - 1))
    short = low + step * ((1 << bits) - 1) < hi  # float32 rounding left the top uncovered: one ulp more
    step = np.where(short, np.nextafter(step.astype(np.float32), np.float32(np.inf)).astype(np.float64), step)
    return low, step


def _integers(values: np.ndarray, low: np.ndarray, step: np.ndarray, bits: int) -> np.ndarray:
    if bits == 0:
        return np.zeros(values.shape, np.int64)
    k = np.round((values - low) / np.where(step > 0, step, 1.0))
    return np.clip(k, 0, (1 << bits) - 1).astype(np.int64)


def dropped_component(q: np.ndarray) -> int:
    """The component of a rotation track (F, 4) whose smallest magnitude is largest: rebuilt, not stored."""
    return int(np.argmax(np.abs(q).min(axis=0)))


def _kept(q: np.ndarray, drop: np.ndarray) -> np.ndarray:
    """(F, 3) the stored components, each key signed so that its dropped one (drop, (F,)) is >= 0."""
    keys = np.arange(q.shape[0])
    signed = np.where(q[keys, drop][:, None] < 0.0, -q, q)
    keep = np.arange(4)[None, :] != drop[:, None]
    return signed[keep].reshape(-1, 3)


def _rebuild(xyz: np.ndarray, drop: np.ndarray) -> np.ndarray:
    """Rotations (F, 4) from stored components, each key's dropped one rebuilt, made unit (each key
    signed so that the dropped component is >= 0, as the decoder has it before it aligns neighbours)."""
    c = np.sqrt(np.maximum(1.0 - np.sum(xyz * xyz, axis=1), 0.0))
    q = np.empty((xyz.shape[0], 4))
    keep = np.arange(4)[None, :] != drop[:, None]
    q[keep] = xyz.reshape(-1)
    q[~keep] = c
    return q / np.linalg.norm(q, axis=1, keepdims=True)


@dataclass
class _Track:
    values: np.ndarray  # (F, 3) what is quantised
    drop: int  # rotations: the dropped component (0..3, or PER_KEY); translations: -1
    index: np.ndarray | None = None  # PER_KEY: each key's dropped component

    @classmethod
    def rotation(cls, q: np.ndarray) -> "_Track":
        drop = dropped_component(q)
        if np.abs(q[:, drop]).min() >= PER_KEY_BELOW:
            return cls(_kept(q, np.full(q.shape[0], drop)), drop)
        index = np.argmax(np.abs(q), axis=1)
        return cls(_kept(q, index), PER_KEY, index)

    def quantised(self, bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(low, step, integers (F, 3)) of the track at `bits`."""
        low, step = _range(self.values, bits)
        return low, step, _integers(self.values, low, step, bits)

    def decode(self, bits: int) -> np.ndarray:
        low, step, ints = self.quantised(bits)
        v = low + ints * step
        if self.drop < 0:
            return v
        return _rebuild(v, np.full(v.shape[0], self.header_drop(bits)) if self.index is None or bits == 0 else self.index)

    def header_drop(self, bits: int) -> int:
        """The dropped-component code the header holds: a constant track stores no keys, so no index either."""
        if self.drop == PER_KEY and bits == 0:
            return int(self.index[0])
        return max(self.drop, 0)

    @staticmethod
    def fields(ints: np.ndarray, bits: int, index: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """(widths (n,), integers (F, n)) of each key's fields as packed: its index first, where it has
        one; a constant track packs nothing."""
        if bits == 0:
            return np.zeros(0, np.int64), np.zeros((ints.shape[0], 0), np.int64)
        if index is None:
            return np.full(3, bits), ints
        return np.array([2, bits, bits, bits]), np.concatenate([index[:, None], ints], axis=1)


class _ClipSearch:
    """One clip's exact skinned shell points, and the error of any per-track decode of it."""

    def __init__(self, skeleton: Skeleton, rotation, translation, scale, joint_points: np.ndarray):
        self.skeleton = skeleton
        self.parents = skeleton.parents
        jc = skeleton.joint_count
        self.rotation, self.translation = rotation, translation
        self.scale3 = np.repeat(scale[..., None], 3, axis=-1)
        self.points = np.ascontiguousarray(joint_points.transpose(0, 2, 1))  # (J, 4, 6): the shell points in each joint's own space
        self.subtree = [np.flatnonzero(self._below(j, jc)) for j in range(jc)]
        self.rot = [_Track.rotation(rotation[:, j]) for j in range(jc)]
        self.tr = [_Track(translation[:, j], -1) for j in range(jc)]
        self.local = tf.trs_to_mat4(translation, rotation, self.scale3)  # (F, J, 4, 4)
        self.exact = global_matrices(skeleton, self.local)
        self.exact_points = self.exact[..., :3, :] @ self.points  # (F, J, 3, 6)
        self.glob = self.exact.copy()
        self.err = np.zeros((rotation.shape[0], jc))  # (F, J): max over the shell points

    def _below(self, j: int, jc: int) -> np.ndarray:
        inside = np.zeros(jc, bool)
        inside[j] = True
        for i in range(j + 1, jc):
            if self.parents[i] >= 0 and inside[self.parents[i]]:
                inside[i] = True
        return inside

    def set_joint(self, j: int, rotation: np.ndarray, translation: np.ndarray) -> None:
        """Decode joint j's tracks as given (F, 4) and (F, 3); its subtree's error follows. Every joint
        below j keeps its transform relative to j, so the subtree moves by one matrix a key, applied in
        one batch (a 256-joint chain took 39 s composed joint by joint, for its deep subtrees)."""
        self.local[:, j] = tf.trs_to_mat4(translation, rotation, self.scale3[:, j])
        p = self.parents[j]
        new = self.local[:, j] if p < 0 else self.glob[:, p] @ self.local[:, j]
        sub = self.subtree[j]
        if sub.size > 1:
            move = new @ np.linalg.inv(self.glob[:, j])  # (F, 4, 4)
            self.glob[:, sub[1:]] = move[:, None] @ self.glob[:, sub[1:]]
        self.glob[:, j] = new
        self._measure(sub)

    def set_all(self, rotation: np.ndarray, translation: np.ndarray) -> None:
        """Decode every joint's tracks as given (F, J, 4) and (F, J, 3), composed afresh."""
        self.local = tf.trs_to_mat4(translation, rotation, self.scale3)
        self.glob = global_matrices(self.skeleton, self.local)
        self._measure(np.arange(len(self.parents)))

    def _measure(self, joints: np.ndarray) -> None:
        moved = self.glob[:, joints, :3, :] @ self.points[joints]
        d = moved - self.exact_points[:, joints]
        self.err[:, joints] = np.sqrt(np.einsum("fjck,fjck->fjk", d, d).max(axis=-1))

    def max_error(self) -> float:
        return float(self.err.max())


def _pack(tracks: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, list[int]]:
    """Words of the tracks' keys, each track's (widths (n,), integers (F, n)) packed key after key, field
    after field, from a whole word; and each track's first word."""
    chunks, firsts, at = [], [], 0
    for widths, ints in tracks:
        firsts.append(at)
        widths = np.asarray(widths, np.int64)
        key_bits = int(widths.sum())
        if key_bits == 0:
            continue
        offsets = np.concatenate([[0], np.cumsum(widths)[:-1]])
        bit = (np.arange(ints.shape[0])[:, None] * key_bits + offsets[None, :]).reshape(-1).astype(np.uint64)
        fields = np.asarray(ints, np.int64).reshape(-1).astype(np.uint64)
        count = -(-ints.shape[0] * key_bits // 32)
        words = np.zeros(count + 1, np.uint64)
        word, shift = bit >> np.uint64(5), bit & np.uint64(31)
        np.bitwise_or.at(words, word, (fields << shift) & np.uint64(0xFFFFFFFF))
        np.bitwise_or.at(words, word + np.uint64(1), (fields << shift) >> np.uint64(32))
        chunks.append(words[:count].astype(np.uint32))
        at += count
    chunks.append(np.zeros(STREAM_PAD_WORDS, np.uint32))
    return np.concatenate(chunks), firsts


def _float_bits(v) -> np.ndarray:
    return np.asarray(v, np.float64).astype(np.float32).view(np.uint32)


def compress(skeleton: Skeleton, clips: list[tuple[np.ndarray, np.ndarray, np.ndarray]], bound_m: float,
             report: Report | None = None) -> CompressedKeys:
    """Quantise every clip's tracks to the smallest widths that keep each clip's keys within KEY_SHARE
    of `bound_m` (progress per clip, crowd.progress)."""
    jc = skeleton.joint_count
    target = KEY_SHARE * bound_m
    joint_points = np.einsum("jab,jkb->jka", skeleton.inverse_bind, shell_points(skeleton))
    rot_bits = np.zeros((len(clips), jc), np.int64)
    tr_bits = np.zeros((len(clips), jc), np.int64)
    decoded, searches, worst, worst_at = [], [], 0.0, (0, 0, 0)
    for c, (rotation, translation, scale) in steps(list(enumerate(clips)), desc="compressing clips", unit="clip", report=report):
        s = _ClipSearch(skeleton, rotation, translation, scale, joint_points)
        rot_bits[c], tr_bits[c] = _uniform_widths(s, target)
        _lower_each(s, rot_bits[c], tr_bits[c], target)
        decoded.append((tf.align_quat_track(np.stack([s.rot[j].decode(rot_bits[c, j]) for j in range(jc)], axis=1), axis=0),
                        np.stack([s.tr[j].decode(tr_bits[c, j]) for j in range(jc)], axis=1)))
        if s.max_error() >= worst:
            f, j = np.unravel_index(int(np.argmax(s.err)), s.err.shape)
            worst, worst_at = s.max_error(), (c, int(f), int(j))
        searches.append(s)
    streams, headers = [], []
    for c, s in enumerate(searches):
        for j in range(jc):
            for track, bits in ((s.rot[j], rot_bits[c, j]), (s.tr[j], tr_bits[c, j])):
                low, step, ints = track.quantised(int(bits))
                streams.append(_Track.fields(ints, int(bits), track.index))
                headers.append((low, step, int(bits), track.header_drop(int(bits))))
    words, firsts = _pack(streams)
    if words.size >= 1 << 24:  # checked before a first word is shifted into a header's 24 bits
        raise ValueError(f"compressed keys need {words.size:,} words; track headers address at most {1 << 24:,}")
    tracks = np.zeros((len(clips) * jc, TRACK_TEXELS, 4), np.uint32)
    for k in range(len(clips) * jc):
        (rlow, rstep, rb, drop), (tlow, tstep, tb, _) = headers[2 * k], headers[2 * k + 1]
        tracks[k, 0, :3], tracks[k, 0, 3] = _float_bits(rlow), (firsts[2 * k] << 8) | (drop << 5) | rb
        tracks[k, 1, :3], tracks[k, 1, 3] = _float_bits(rstep), (firsts[2 * k + 1] << 8) | tb
        tracks[k, 2, :3] = _float_bits(tlow)
        tracks[k, 3, :3] = _float_bits(tstep)
    return CompressedKeys(words, tracks.reshape(len(clips), jc, TRACK_TEXELS, 4), decoded, float(bound_m), worst, worst_at,
                          rot_bits, tr_bits)


def _set_all(s: _ClipSearch, rb: int | None, tb: int | None) -> float:
    """Every joint's tracks at widths rb and tb (None: exact); the clip's error."""
    jc = len(s.rot)
    rotation = s.rotation if rb is None else np.stack([s.rot[j].decode(rb) for j in range(jc)], axis=1)
    translation = s.translation if tb is None else np.stack([s.tr[j].decode(tb) for j in range(jc)], axis=1)
    s.set_all(rotation, translation)
    return s.max_error()


def _uniform_widths(s: _ClipSearch, bound_m: float) -> tuple[int, int]:
    """The smallest rotation width with exact translations, and translation width with exact
    rotations, each within half the bound; then both raised together until the clip is within it."""
    rb = _smallest(lambda b: _set_all(s, b, None) <= 0.5 * bound_m)
    tb = _smallest(lambda b: _set_all(s, None, b) <= 0.5 * bound_m)
    while _set_all(s, rb, tb) > bound_m and max(rb, tb) < MAX_BITS:
        rb, tb = min(rb + 1, MAX_BITS), min(tb + 1, MAX_BITS)
    return rb, tb


def _smallest(fits) -> int:
    """The smallest width in 0..MAX_BITS that `fits` (bisection: the error falls as widths grow), else MAX_BITS."""
    low, high = 0, MAX_BITS
    while low < high:
        mid = (low + high) // 2
        low, high = (low, mid) if fits(mid) else (mid + 1, high)
    return low


def _lower_each(s: _ClipSearch, rot_bits: np.ndarray, tr_bits: np.ndarray, bound_m: float) -> None:
    """From the uniform widths (already set in `s`), each track lowered in turn while the clip stays
    within the bound, leaves first: a leaf's error reaches no other joint."""
    if s.max_error() > bound_m:
        return  # MAX_BITS everywhere does not reach the bound: the caller reports the error it has
    for j in reversed(range(len(s.rot))):
        for bits in (rot_bits, tr_bits):
            while bits[j] > 0:
                bits[j] -= 1
                s.set_joint(j, s.rot[j].decode(int(rot_bits[j])), s.tr[j].decode(int(tr_bits[j])))
                if s.max_error() > bound_m:
                    bits[j] += 1
                    s.set_joint(j, s.rot[j].decode(int(rot_bits[j])), s.tr[j].decode(int(tr_bits[j])))
                    break
