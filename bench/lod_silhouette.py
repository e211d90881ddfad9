"""How far each coarser LOD's silhouette is from LOD0's where the renderer switches to it.

Contract: ``silhouette_iou(character, lod_distances, size, fov_y)`` → one row per LOD k >= 1 (that the
character has), with the intersection over union of LOD k's and LOD0's silhouettes at LOD k's switch
distance, for the default pieces (the first of each variation group), in poses across the first
looping clips and from the front and the side:
``{"lod", "distance_m", "height_px", "triangles", "triangles_lod0", "iou_min", "iou_mean", "pixel_iou_min",
"pixel_iou_mean", "views"}``.

Everything is float64 on the CPU: the poses from crowd.anim.reference, linear-blend skinning of each
LOD's own vertices, and a rasteriser of its own (below) with 4 x 4 samples a pixel, so the answer does
not depend on a GPU. The figure is drawn as a 45-degree camera at `size` shows it at that distance (an
orthographic projection of one agent: at 26 px tall, perspective across the figure changes nothing a
pixel can show). The IoU is over the samples, i.e. of the coverage masks at 4 times the pixel size.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from crowd.anim import reference
from crowd.asset.lod import with_generated_lods
from crowd.asset.model import Character

SAMPLES = 4  # per pixel side
PHASES = (0.0, 0.25, 0.5, 0.75)


def _pieces(character: Character, lod: int):
    """The meshes a default agent wears at `lod` (the first piece of each variation group)."""
    seen, out = set(), []
    for m in character.meshes:
        if m.lod != lod:
            continue
        if m.group:
            if m.group in seen:
                continue
            seen.add(m.group)
        out.append(m)
    return out


def rasterise(triangles: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Coverage mask (H, W) of 2D triangles (T, 3, 2) in sample units (sample centres at k + 0.5)."""
    mask = np.zeros(shape, bool)
    h, w = shape
    for a, b, c in triangles:
        area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        if abs(area) < 1e-12:
            continue
        x0, x1 = max(int(math.floor(min(a[0], b[0], c[0]))), 0), min(int(math.ceil(max(a[0], b[0], c[0]))), w)
        y0, y1 = max(int(math.floor(min(a[1], b[1], c[1]))), 0), min(int(math.ceil(max(a[1], b[1], c[1]))), h)
        if x0 >= x1 or y0 >= y1:
            continue
        px, py = np.meshgrid(np.arange(x0, x1) + 0.5, np.arange(y0, y1) + 0.5)
        sign = 1.0 if area > 0 else -1.0  # either winding: a silhouette has no back faces
        inside = np.ones(px.shape, bool)
        for p, q in ((a, b), (b, c), (c, a)):
            inside &= sign * ((q[0] - p[0]) * (py - p[1]) - (q[1] - p[1]) * (px - p[0])) >= 0
        mask[y0:y1, x0:x1] |= inside
    return mask


def generated_lods(character: Character, repeats: int = 1) -> tuple[Character, list[float]]:
    """`character` as drawn: with its own LODs where its file has them (no time), else with LODs made
    by crowd.asset.lod without the cache, `repeats` times (the seconds each took; the last result)."""
    if any(m.lod > 0 for m in character.meshes) and character.lod_distances is None:
        return character, []
    base = dataclasses.replace(character, meshes=[m for m in character.meshes if m.lod == 0], lod_distances=None)
    seconds = []
    for _ in range(max(repeats, 1)):
        start = time.perf_counter()
        made = with_generated_lods(base, cache=False)
        seconds.append(time.perf_counter() - start)
    return made, seconds


def silhouette_iou(character: Character, lod_distances, size: tuple[int, int] = (1920, 1080), fov_y: float = 45.0) -> list[dict]:
    sk = character.skeleton
    clips = [c for c in character.clips if c.loop][:3] or character.clips[:1]
    matrices = np.concatenate([reference.skinning_matrices(sk, reference.sample_clip(sk, c, np.array(PHASES))) for c in clips])
    lods = sorted({m.lod for m in character.meshes})
    skinned = {}
    for lod in lods:
        points, tris, base = [], [], 0
        for m in _pieces(character, lod):
            points.append(reference.skin_points(matrices, m.positions, m.joints, m.weights))  # (P, V, 3)
            tris.append(np.asarray(m.indices, np.int64).reshape(-1, 3) + base)
            base += len(m.positions)
        skinned[lod] = (np.concatenate(points, axis=1), np.concatenate(tris), sum(len(t) for t in tris))
    rows = []
    for lod in [k for k in lods[1:] if k <= len(lod_distances)]:  # the colour LODs (a coarser one casts shadows only)
        distance = float(lod_distances[lod - 1])
        metres_per_sample = 2.0 * distance * math.tan(math.radians(fov_y) / 2.0) / size[1] / SAMPLES
        ious, pixel_ious, height = [], [], 0.0
        for pose in range(matrices.shape[0]):
            for axis in (0, 2):  # seen from the front (x across) and from the side (z across)
                masks = []
                for k in (0, lod):
                    points, tris, _ = skinned[k]
                    uv = np.stack([points[pose, :, axis], -points[pose, :, 1]], axis=1) / metres_per_sample
                    masks.append(uv)
                lo = np.minimum(masks[0].min(axis=0), masks[1].min(axis=0)) - 2.0
                hi = np.maximum(masks[0].max(axis=0), masks[1].max(axis=0)) + 2.0
                shape = tuple(int(v) for v in np.ceil(hi - lo)[::-1])
                shape = tuple(-(-v // SAMPLES) * SAMPLES for v in shape)  # whole pixels
                cover = [rasterise((uv - lo)[skinned[k][1]], shape) for uv, k in zip(masks, (0, lod))]
                ious.append(_iou(*cover))
                pixels = [c.reshape(shape[0] // SAMPLES, SAMPLES, shape[1] // SAMPLES, SAMPLES).mean(axis=(1, 3)) >= 0.5 for c in cover]
                pixel_ious.append(_iou(*pixels))
                height = max(height, float(np.ptp(masks[0][:, 1])) / SAMPLES)
        rows.append({"lod": lod, "distance_m": distance, "height_px": round(height, 1), "triangles": skinned[lod][2],
                     "triangles_lod0": skinned[0][2], "iou_min": round(float(min(ious)), 4), "iou_mean": round(float(np.mean(ious)), 4),
                     "pixel_iou_min": round(float(min(pixel_ious)), 4), "pixel_iou_mean": round(float(np.mean(pixel_ious)), 4),
                     "views": len(ious)})
    return rows


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.count_nonzero(a | b)
    return np.count_nonzero(a & b) / union if union else 1.0
