"""Triangle order for the GPU's vertex reuse (Tom Forsyth's "linear-speed vertex cache optimisation").

Why: on an H100 the crowd's draws are bound by vertex processing (chiefly fetching vertex attributes,
docs/BENCHMARKS.md), so every vertex the GPU processes twice costs. Reordering triangles so that
neighbours share vertices cuts vertex shader invocations per triangle; the geometry is unchanged.
Why by hand: meshoptimizer does this in C, but it ships no wheel for our Python versions (only an alpha sdist), and
the algorithm is short. Measured against meshoptimizer's optimizeVertexCache on the built-in zombie
(`crowd-bench vertex-cache`, docs/BENCHMARKS.md), this order shades 0.789 vertices a triangle in the
batch model below and meshoptimizer's 0.792: it stays. It runs once per mesh at load time (its time
against meshoptimizer's: docs/BENCHMARKS.md and docs/ASSETS.md). ``best_triangle_order`` keeps the source order where
that is already better (the zombie's merged LOD3: 0.797 against 0.819).
"""

from __future__ import annotations

import heapq

import numpy as np

CACHE_SIZE = 32
_DECAY_POWER = 1.5
_LAST_TRI_SCORE = 0.75
_VALENCE_SCALE = 2.0
_VALENCE_POWER = 0.5


def _vertex_score(position: int, remaining: int) -> float:
    if remaining == 0:
        return -1.0
    score = 0.0
    if position >= 0:
        if position < 3:
            score = _LAST_TRI_SCORE
        else:
            score = (1.0 - (position - 3) / (CACHE_SIZE - 3)) ** _DECAY_POWER
    return score + _VALENCE_SCALE * remaining ** -_VALENCE_POWER


def optimize_triangle_order(indices: np.ndarray, vertex_count: int) -> np.ndarray:
    """The same triangles (uint32, flat) in an order that reuses recently shaded vertices."""
    tris = np.asarray(indices, dtype=np.int64).reshape(-1, 3)
    t = len(tris)
    if t <= 1:
        return np.asarray(indices, dtype=np.uint32).copy()
    vert_tris: list[list[int]] = [[] for _ in range(vertex_count)]
    for i, (a, b, c) in enumerate(tris.tolist()):
        vert_tris[a].append(i)
        vert_tris[b].append(i)
        vert_tris[c].append(i)
    remaining = [len(v) for v in vert_tris]
    vscore = [_vertex_score(-1, r) for r in remaining]
    tri_list = tris.tolist()
    tscore = [vscore[a] + vscore[b] + vscore[c] for a, b, c in tri_list]
    emitted = [False] * t
    cache: list[int] = []
    out: list[int] = []
    best = int(np.argmax(tscore))
    # The best of the rest (the highest score, the first on ties) from a heap of (-score, triangle), each
    # changed score pushed when next needed: scanning every triangle each time the cache runs dry made
    # meshes of many parts (a merged modular character, or one whose triangles share no vertex) quadratic.
    rest = [(-score, i) for i, score in enumerate(tscore)]
    heapq.heapify(rest)
    changed: set[int] = set()
    for _ in range(t):
        if best < 0:  # nothing in the cache touches a remaining triangle: take the best of the rest
            for i in changed:
                if not emitted[i]:
                    heapq.heappush(rest, (-tscore[i], i))
            changed.clear()
            while emitted[rest[0][1]] or -rest[0][0] != tscore[rest[0][1]]:  # gone, or an old score
                heapq.heappop(rest)
            best = rest[0][1]
        emitted[best] = True
        tri = tri_list[best]
        out.append(best)
        for v in tri:
            vert_tris[v].remove(best)
            remaining[v] -= 1
        cache = tri + [v for v in cache if v not in tri]
        evicted = cache[CACHE_SIZE:]
        cache = cache[:CACHE_SIZE]
        touched = set()
        for pos, v in enumerate(cache):
            vscore[v] = _vertex_score(pos, remaining[v])
            touched.update(vert_tris[v])
        for v in evicted:
            vscore[v] = _vertex_score(-1, remaining[v])
            touched.update(vert_tris[v])
        best, best_score = -1, -1.0
        changed.update(touched)
        for i in touched:
            a, b, c = tri_list[i]
            s = vscore[a] + vscore[b] + vscore[c]
            tscore[i] = s
            if s > best_score:
                best, best_score = i, s
    return tris[np.asarray(out)].reshape(-1).astype(np.uint32)


def shaded_vertices_per_triangle(indices: np.ndarray, batch_vertices: int = 32) -> float:
    """Vertex shader invocations per triangle when the GPU shades triangles in batches of at most
    `batch_vertices` distinct vertices and reuses nothing across batches (how recent NVIDIA GPUs work)."""
    tris = np.asarray(indices).reshape(-1, 3).tolist()
    shaded, seen = 0, set()
    for tri in tris:
        if len(seen | set(tri)) > batch_vertices:
            shaded += len(seen)
            seen = set()
        seen.update(tri)
    return (shaded + len(seen)) / max(len(tris), 1)


def best_triangle_order(indices: np.ndarray, vertex_count: int) -> np.ndarray:
    """``optimize_triangle_order``'s result, or the source order (as uint32) where that shades fewer
    vertices a triangle (``shaded_vertices_per_triangle``)."""
    source = np.asarray(indices, dtype=np.uint32)
    optimised = optimize_triangle_order(source, vertex_count)
    return optimised if shaded_vertices_per_triangle(optimised) < shaded_vertices_per_triangle(source) else source.copy()
