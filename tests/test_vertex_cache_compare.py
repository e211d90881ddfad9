"""crowd-bench vertex-cache (bench/vertex_cache_compare.py): its FIFO model on known index streams, and
its one-line answer where meshoptimizer (no wheel, not a dependency) is missing."""

import importlib.util
import subprocess
import sys

import numpy as np
import pytest

from bench.vertex_cache_compare import fifo_misses_per_triangle
from conftest import ROOT


def test_the_fifo_model_counts_misses():
    strip = np.array([[k, k + 1, k + 2] for k in range(100)]).ravel()  # each triangle brings one new vertex
    assert fifo_misses_per_triangle(strip) == pytest.approx(102 / 100)
    soup = np.arange(300)  # no vertex shared
    assert fifo_misses_per_triangle(soup) == 3.0
    # A vertex evicted from a 4-entry FIFO is a miss again.
    assert fifo_misses_per_triangle(np.array([0, 1, 2, 3, 4, 5, 0, 1, 2]), size=4) == 3.0


@pytest.mark.skipif(importlib.util.find_spec("meshoptimizer") is not None, reason="meshoptimizer is importable here")
def test_without_meshoptimizer_the_command_answers_in_one_line():
    r = subprocess.run([sys.executable, "-m", "bench", "vertex-cache"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "meshoptimizer is not importable" in r.stderr


def test_the_best_order_is_never_worse_than_the_source_or_the_optimised_one(zombie):
    from crowd.asset.vertex_cache import best_triangle_order, optimize_triangle_order, shaded_vertices_per_triangle

    kept_source = 0
    for m in zombie.meshes:
        best = best_triangle_order(m.indices, len(m.positions))
        assert sorted(map(tuple, np.sort(best.reshape(-1, 3), axis=1).tolist())) == sorted(map(tuple, np.sort(m.indices.reshape(-1, 3), axis=1).tolist()))
        shaded = shaded_vertices_per_triangle(best)
        assert shaded <= shaded_vertices_per_triangle(m.indices) and shaded <= shaded_vertices_per_triangle(optimize_triangle_order(m.indices, len(m.positions)))
        kept_source += int(np.array_equal(best, m.indices))
    assert kept_source >= 2  # the merged LOD3 meshes, at least
