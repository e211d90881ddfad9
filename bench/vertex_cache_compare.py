"""The hand-written triangle order (crowd/asset/vertex_cache.py) against meshoptimizer's, on every mesh
of the built-in zombie (or a model's): vertex shader invocations per triangle in the batch model of
NVIDIA's GPUs (batches of 32 distinct vertices, no reuse across them: what bounds the skinned draw,
docs/BENCHMARKS.md "Vertex layout"), the miss ratio of a 32-entry FIFO cache, and the time each takes.

meshoptimizer is not a dependency: its Python package is an alpha sdist (0.2.30a0) with no wheel, so
``crowd-bench vertex-cache`` needs it built and importable (docs/BENCHMARKS.md says how) and answers in
one line when it is not.
"""

from __future__ import annotations

import time

import numpy as np

from crowd.asset.model import Character
from crowd.asset.vertex_cache import CACHE_SIZE, optimize_triangle_order, shaded_vertices_per_triangle


def fifo_misses_per_triangle(indices: np.ndarray, size: int = CACHE_SIZE) -> float:
    """Average cache miss ratio of a FIFO post-transform cache of `size` vertices."""
    cache: list[int] = []
    misses = 0
    for v in np.asarray(indices).tolist():
        if v not in cache:
            misses += 1
            cache.append(v)
            if len(cache) > size:
                cache.pop(0)
    return misses / max(len(indices) // 3, 1)


def _same_triangles(a: np.ndarray, b: np.ndarray) -> bool:
    key = lambda x: np.sort(np.sort(np.asarray(x).reshape(-1, 3), axis=1).view([("", x.dtype)] * 3).ravel())
    return bool(np.array_equal(key(a), key(b)))


def compare(character: Character) -> dict:
    """Per mesh and in total (triangle-weighted): the three orders' batch and FIFO figures and times."""
    import meshoptimizer

    meshes = [(m.name, m.indices, len(m.positions)) for m in character.meshes]
    meshes += [(r.name, r.indices, len(r.positions)) for p in character.props.values() for r in p.lods]
    rows, totals = [], {k: np.zeros(2) for k in ("source", "hand", "meshoptimizer")}
    triangles = 0
    for name, indices, vertex_count in meshes:
        indices = np.ascontiguousarray(indices, np.uint32)
        t0 = time.perf_counter()
        hand = optimize_triangle_order(indices, vertex_count)
        hand_ms = (time.perf_counter() - t0) * 1e3
        mopt = np.empty_like(indices)
        t0 = time.perf_counter()
        meshoptimizer.optimize_vertex_cache(mopt, indices, len(indices), vertex_count)
        mopt_ms = (time.perf_counter() - t0) * 1e3
        row = {"mesh": name, "triangles": len(indices) // 3, "ms": {"hand": round(hand_ms, 3), "meshoptimizer": round(mopt_ms, 3)}}
        for key, order in (("source", indices), ("hand", hand), ("meshoptimizer", mopt)):
            if not _same_triangles(order, indices):
                raise ValueError(f"{key} order of {name!r} changed the triangles")
            figures = np.array([shaded_vertices_per_triangle(order), fifo_misses_per_triangle(order)])
            row[key] = {"batch32_shaded_per_triangle": round(float(figures[0]), 4), "fifo32_misses_per_triangle": round(float(figures[1]), 4)}
            totals[key] += figures * (len(indices) // 3)
        triangles += len(indices) // 3
        rows.append(row)
    total = {key: {"batch32_shaded_per_triangle": round(float(v[0] / triangles), 4), "fifo32_misses_per_triangle": round(float(v[1] / triangles), 4)}
             for key, v in totals.items()}
    total["ms"] = {k: round(sum(r["ms"][k] for r in rows), 2) for k in ("hand", "meshoptimizer")}
    return {"meshes": rows, "total": total, "meshoptimizer": getattr(meshoptimizer, "__version__", "0.2.30a0")}
