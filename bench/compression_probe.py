"""Probe (issue 21, point 4): how small an error-bounded quantised bake of a character's clips can be,
before any of it is built into the bake or the processor. It decides the format the GPU will decode.

Each clip is taken at its own keys (the 30 fps bake's frames for the built-in zombie), every joint's
rotation and translation a track. A track that never moves (within 1e-7 rad or 1e-7 m) is stored once;
a moving one is quantised to its own range, per component, in b bits: ACL's range reduction. Two
rotation encodings are tried: all four components, and x, y, z with w rebuilt (each key's sign chosen so
that w >= 0; the GPU would realign neighbours as it does for blends). The error is ACL's: the float64
skinned 3 cm shell of every joint at every key, the decoded keys against the clip's own.

Bits are chosen two ways: one width for every moving rotation and one for every translation (the
smallest meeting the bound), and per track, ACL-style: from the uniform widths, each track in turn is
lowered as far as the clip stays within the bound.

Bytes count the key data at its bits (packed per track), plus per track a 4-byte header (bits, flags)
and its range or constant value in float32. The f32 bake stores 32 bytes per joint and key (two RGBA32F
texels). Key dropping, which ACL also does, is not tried here.

Run: python -m bench.compression_probe [--json out.json] [--model file.glb]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from crowd.anim import accuracy
from crowd.asset.model import Character
from crowd.asset.pose import LocalPose, global_matrices, sample_clip

CONSTANT = 1e-7
BOUNDS_MM = (0.5, 0.1)


def keys_of(character: Character, clip, fps: float = 30.0) -> LocalPose:
    """The clip sampled at `fps` keys over its duration (closing key included), from its source keys."""
    duration = max(clip.end - clip.start, 1e-6)
    count = max(2, int(math.ceil(duration * fps - 1e-5)) + 1)
    return sample_clip(character.skeleton, clip, np.linspace(0.0, 1.0, count))


def _quantise(values: np.ndarray, bits: int) -> np.ndarray:
    """Per component of a track (F, C), to `bits` bits over the track's own range, and back."""
    low, high = values.min(axis=0), values.max(axis=0)
    span = np.where(high > low, high - low, 1.0)
    steps = (1 << bits) - 1
    return low + np.round((values - low) / span * steps) / steps * span


def decode_rotation(q: np.ndarray, bits: int, drop_w: bool) -> np.ndarray:
    """A rotation track (F, 4) xyzw through the encoding and back, made unit."""
    if drop_w:
        q = np.where(q[:, 3:4] < 0.0, -q, q)
        xyz = _quantise(q[:, :3], bits)
        w = np.sqrt(np.maximum(1.0 - np.sum(xyz * xyz, axis=1), 0.0))
        q = np.concatenate([xyz, w[:, None]], axis=1)
    else:
        q = _quantise(q, bits)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


class ClipTracks:
    """One clip's keys and what decoding them with given bit widths costs in error."""

    def __init__(self, character: Character, clip):
        self.skeleton = character.skeleton
        self.pose = keys_of(character, clip)
        self.name = clip.name
        self.frames, self.joints = self.pose.rotation.shape[:2]
        rot, tr = self.pose.rotation, self.pose.translation
        angle = 2.0 * np.arccos(np.clip(np.abs(np.einsum("fjc,jc->fj", rot, rot[0])), 0.0, 1.0))
        self.rot_moves = angle.max(axis=0) > CONSTANT
        self.tr_moves = np.abs(tr - tr[0]).max(axis=(0, 2)) > CONSTANT
        self.points = accuracy.shell_points(self.skeleton)
        self.truth = self._skin(self.pose)

    def _skin(self, pose: LocalPose) -> np.ndarray:
        return global_matrices(self.skeleton, pose) @ self.skeleton.inverse_bind[None]

    def error_mm(self, rot_bits: np.ndarray, tr_bits: np.ndarray, drop_w: bool) -> float:
        """Largest shell error (mm) of the clip decoded with per-joint widths (0: not moving)."""
        rot = self.pose.rotation.copy()
        tr = self.pose.translation.copy()
        for j in range(self.joints):
            rot[:, j] = decode_rotation(rot[:, j], int(rot_bits[j]), drop_w) if self.rot_moves[j] else rot[0, j]
            tr[:, j] = _quantise(tr[:, j], int(tr_bits[j])) if self.tr_moves[j] else tr[0, j]
        decoded = self._skin(LocalPose(tr, rot, self.pose.scale))
        return float(accuracy.shell_error(decoded, self.truth, self.points).max() * 1e3)

    def nbytes(self, rot_bits: np.ndarray, tr_bits: np.ndarray, drop_w: bool) -> int:
        comps = 3 if drop_w else 4
        total = 0
        for j in range(self.joints):
            total += 4 + (8 * comps + math.ceil(self.frames * comps * rot_bits[j] / 8) if self.rot_moves[j] else 16)
            total += 4 + (24 + math.ceil(self.frames * 3 * tr_bits[j] / 8) if self.tr_moves[j] else 12)
        return total


def uniform_bits(clips: list[ClipTracks], bound_mm: float, drop_w: bool) -> tuple[int, int]:
    """The smallest (rotation, translation) widths, the same for every moving track, within the bound:
    each width lowered alone with the other at 24 bits, then both checked together (raised if not)."""
    def worst(rb, tb):
        return max(c.error_mm(np.full(c.joints, rb), np.full(c.joints, tb), drop_w) for c in clips)

    rb = next(b for b in range(4, 25) if worst(b, 24) <= 0.5 * bound_mm)
    tb = next(b for b in range(4, 25) if worst(24, b) <= 0.5 * bound_mm)
    while worst(rb, tb) > bound_mm:
        rb, tb = rb + 1, tb + 1
    return rb, tb


def per_track_bits(clip: ClipTracks, start: tuple[int, int], bound_mm: float, drop_w: bool) -> tuple[np.ndarray, np.ndarray]:
    """From the uniform widths, each moving track lowered in turn (joints from the leaves up, whose
    errors reach the fewest others) while the clip stays within the bound."""
    rot = np.where(clip.rot_moves, start[0], 0)
    tr = np.where(clip.tr_moves, start[1], 0)
    for j in reversed(range(clip.joints)):
        for bits, moves in ((rot, clip.rot_moves), (tr, clip.tr_moves)):
            while moves[j] and bits[j] > 3:
                bits[j] -= 1
                if clip.error_mm(rot, tr, drop_w) > bound_mm:
                    bits[j] += 1
                    break
    return rot, tr


def probe(character: Character) -> dict:
    clips = [ClipTracks(character, c) for c in character.clips]
    f32_bytes = sum(32 * c.frames * c.joints for c in clips)
    report = {"model": character.name, "clips": len(clips), "joints": clips[0].joints, "keys": sum(c.frames for c in clips),
              "f32_bytes": f32_bytes,
              "moving_rotation_tracks": int(sum(c.rot_moves.sum() for c in clips)),
              "moving_translation_tracks": int(sum(c.tr_moves.sum() for c in clips)),
              "tracks": 2 * sum(c.joints for c in clips), "rows": []}
    for bound in BOUNDS_MM:
        for drop_w in (False, True):
            rb, tb = uniform_bits(clips, bound, drop_w)
            uniform = [(np.full(c.joints, rb), np.full(c.joints, tb)) for c in clips]
            tuned = [per_track_bits(c, (rb, tb), bound, drop_w) for c in clips]
            for scheme, widths in (("uniform", uniform), ("per track", tuned)):
                nbytes = sum(c.nbytes(r, t, drop_w) for c, (r, t) in zip(clips, widths))
                err = max(c.error_mm(r, t, drop_w) for c, (r, t) in zip(clips, widths))
                moving = [b for c, (r, t) in zip(clips, widths) for b in r[c.rot_moves]]
                report["rows"].append({"bound_mm": bound, "rotation": "xyz, w rebuilt" if drop_w else "xyzw", "bits": scheme,
                                       "rotation_bits": rb, "translation_bits": tb,
                                       "mean_rotation_bits": round(float(np.mean(moving)), 2) if moving else 0.0,
                                       "bytes": nbytes, "ratio": round(f32_bytes / nbytes, 2), "max_error_mm": round(err, 4)})
    return report


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, help="a .glb/.gltf (default: the built-in zombie)")
    parser.add_argument("--json", type=Path, help="write the report here as JSON (atomically)")
    args = parser.parse_args(argv)
    from crowd.asset.gltf import load_character

    report = probe(load_character(args.model))
    print(f"{report['model']}: {report['clips']} clips, {report['joints']} joints, {report['keys']} keys; f32 bake "
          f"{report['f32_bytes']:,} B; moving tracks: {report['moving_rotation_tracks']} rotations, "
          f"{report['moving_translation_tracks']} translations of {report['tracks']}")
    print(f"{'bound mm':>8} {'rotation':>14} {'bits':>10} {'rot b':>6} {'tr b':>5} {'mean rot b':>10} {'bytes':>9} {'ratio':>6} {'max mm':>8}")
    for r in report["rows"]:
        print(f"{r['bound_mm']:>8} {r['rotation']:>14} {r['bits']:>10} {r['rotation_bits']:>6} {r['translation_bits']:>5} "
              f"{r['mean_rotation_bits']:>10} {r['bytes']:>9,} {r['ratio']:>6} {r['max_error_mm']:>8}")
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(args.json, json.dumps(report, indent=1).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
