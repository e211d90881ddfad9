"""The silhouette measure behind `crowd-bench lod` (bench/lod_silhouette.py): its rasteriser against
exact areas, and the built-in zombie's coarser LODs against the IoU they were accepted at."""

import numpy as np
import pytest

from bench.lod_silhouette import rasterise, silhouette_iou


def test_rasteriser_covers_a_triangle_as_its_area_says():
    rng = np.random.default_rng(3)
    for _ in range(20):
        tri = rng.uniform(0, 200, (1, 3, 2))
        a, b, c = tri[0]
        area = abs((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])) / 2
        perimeter = sum(np.linalg.norm(p - q) for p, q in ((a, b), (b, c), (c, a)))
        covered = np.count_nonzero(rasterise(tri, (200, 200)))
        assert abs(covered - area) <= perimeter + 3  # samples along the edges go either way
    # Winding does not matter, and a degenerate triangle covers nothing.
    tri = np.array([[[10.0, 10.0], [90.0, 10.0], [10.0, 90.0]]])
    assert np.array_equal(rasterise(tri, (100, 100)), rasterise(tri[:, ::-1], (100, 100)))
    assert not rasterise(np.array([[[0.0, 0.0], [50.0, 50.0], [100.0, 100.0]]]), (100, 100)).any()


def test_a_lod_identical_to_lod0_has_iou_one(zombie):
    import dataclasses

    lod0 = [m for m in zombie.meshes if m.lod == 0]
    copy = dataclasses.replace(zombie, meshes=lod0 + [dataclasses.replace(m, lod=1) for m in lod0])
    (row,) = silhouette_iou(copy, (30.0, 60.0, 90.0))
    assert row["iou_min"] == 1.0 and row["pixel_iou_min"] == 1.0 and row["triangles"] == row["triangles_lod0"]


def test_the_zombies_lods_keep_their_silhouette_at_their_switch_distance(zombie):
    """The IoU figures of docs/BENCHMARKS.md ("The coarse LOD") at the default distances, as floors:
    a regenerated mesh that loses its silhouette fails here."""
    rows = {r["lod"]: r for r in silhouette_iou(zombie, (14.0, 40.0, 90.0))}
    for lod, floor in ((1, 0.95), (2, 0.84), (3, 0.70)):
        assert rows[lod]["iou_min"] >= floor and rows[lod]["pixel_iou_min"] >= floor - 0.02, rows[lod]
