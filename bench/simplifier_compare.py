"""The simplifier behind the LODs made for imported characters (crowd/asset/simplify.py) against the ones
a user could install: fast-simplification and pyfqmr (wheels; both the Fast-Quadric-Mesh-Simplification
algorithm) and meshoptimizer (no wheel: an alpha sdist, built by hand for this comparison only).

Each candidate simplifies every LOD0 mesh of a character to the triangle count of the generated LOD of
that mesh, so all of them spend the same triangles; then each LOD's silhouette is measured against LOD0
at the generated LOD's switch distance (bench/lod_silhouette.py), with the time each candidate took and
how many triangles sample far-apart parts of the texture (``wide_uv_triangles``: a seam smeared).

How the attributes follow where a candidate knows only positions:
- fast-simplification and pyfqmr get the welded points (position, skin and morph deltas alike; crowd's
  weld) and move the vertices they keep; each kept vertex takes the skin, normal and texture coordinates
  of the source point nearest its new position (the collapse map of fast-simplification names the point
  it came from, but not where a merged vertex went across a seam, which they do not know of);
- meshoptimizer (``simplify``, its default options, no error limit) keeps source vertices, so each keeps
  its own attributes, as crowd's does; it finds seams itself from vertices that share a position.
A candidate that is not importable is left out, with one line saying so.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from crowd.asset.lod import lod_mesh
from crowd.asset.model import Character, SkinnedMesh
from crowd.asset.morph_transfer import nearest_vertices
from crowd.asset.simplify import weld
from crowd.settings import DEFAULTS

from .lod_silhouette import generated_lods, silhouette_iou

CANDIDATES = ("crowd", "meshoptimizer", "fast-simplification", "pyfqmr")
WIDE_UV = 0.25  # a triangle whose texture coordinates span more than a quarter of the texture on an axis


def _moved_mesh(mesh: SkinnedMesh, lod: int, positions: np.ndarray, triangles: np.ndarray) -> SkinnedMesh:
    """A LOD of `mesh` at new `positions`, each vertex with the attributes of the source vertex nearest it."""
    near, _ = nearest_vertices(mesh.positions, positions)
    taken = lod_mesh(mesh, lod, near, np.zeros(0, np.uint32))
    return dataclasses.replace(taken, positions=np.asarray(positions, np.float32), indices=np.asarray(triangles, np.uint32).reshape(-1),
                               morph_targets=None, morph_positions=None, morph_normals=None)


def _points(mesh: SkinnedMesh):
    w = weld(mesh)
    first = w.source[np.unique(w.vertex_point, return_index=True)[1]]
    return np.asarray(mesh.positions[first], np.float64), w.vertex_point[w.triangles], w


def simplify_with(name: str, mesh: SkinnedMesh, lod: int, triangles: int) -> SkinnedMesh:
    """`mesh` simplified by candidate `name` to at most about `triangles` triangles, as its LOD `lod`."""
    if name == "meshoptimizer":
        import meshoptimizer

        w = weld(mesh)
        positions = np.ascontiguousarray(mesh.positions[w.source], np.float32)
        indices = np.ascontiguousarray(w.triangles.reshape(-1), np.uint32)
        out = np.zeros(len(indices), np.uint32)
        count = meshoptimizer.simplify(out, indices, positions, target_index_count=3 * triangles, target_error=1.0)
        used, local = np.unique(out[:count], return_inverse=True)
        return lod_mesh(mesh, lod, w.source[used], local.astype(np.uint32))
    points, tris, _ = _points(mesh)
    if name == "fast-simplification":
        import fast_simplification

        moved, faces = fast_simplification.simplify(points, tris.astype(np.int64), target_count=triangles)
        return _moved_mesh(mesh, lod, moved, faces)
    import pyfqmr

    simplifier = pyfqmr.Simplify()
    simplifier.setMesh(points, tris.astype(np.int32))
    simplifier.simplify_mesh(target_count=triangles, aggressiveness=7, preserve_border=True, verbose=False)
    moved, faces, _ = simplifier.getMesh()
    return _moved_mesh(mesh, lod, moved, faces)


def compare(character: Character, size: tuple[int, int] = (1920, 1080)) -> dict:
    """For each candidate that imports: per LOD the triangles and silhouette IoU at the generated LOD's
    switch distance, and its time for every mesh and LOD (crowd's includes measuring its ladder)."""
    base = dataclasses.replace(character, meshes=[m for m in character.meshes if m.lod == 0], lod_distances=None)
    made, seconds = generated_lods(base, 1)
    distances = tuple(d / DEFAULTS["lod_error_px"] for d in made.lod_distances)
    out = {"character": character.name, "lod_distances": list(distances), "candidates": {}, "missing": []}
    for name in CANDIDATES:
        if name == "crowd":
            lods, spent = made, seconds[0]
        else:
            try:
                start = time.perf_counter()
                coarser = [simplify_with(name, src, m.lod, m.triangle_count) for m in made.meshes if m.lod > 0
                           for src in [next(s for s in base.meshes if s.piece == m.piece)]]
                spent = time.perf_counter() - start
            except ImportError as exc:
                out["missing"].append(f"{name}: not importable ({exc})")
                continue
            lods = dataclasses.replace(base, meshes=base.meshes + coarser, lod_distances=distances)
        rows = silhouette_iou(lods, distances, size)
        out["candidates"][name] = {"seconds": round(spent, 3), "rows": [{**{k: r[k] for k in ("lod", "distance_m", "triangles", "triangles_lod0", "iou_min",
                                                                                              "iou_mean")}, "wide_uv": wide_uv_triangles(lods, r["lod"])}
                                                                        for r in rows]}
    out["wide_uv_lod0"] = wide_uv_triangles(base, 0)
    return out


def wide_uv_triangles(character: Character, lod: int, span: float = WIDE_UV) -> int:
    """Textured triangles of LOD `lod` whose texture coordinates span more than `span` on an axis: where
    a simplifier joined the two sides of a UV seam, a triangle's corners sample far-apart parts of the
    texture (a smear). The source has its own few (LOD0's count is the baseline)."""
    count = 0
    for m in character.meshes:
        if m.lod == lod and m.uvs is not None and m.indices.size:
            uv = m.uvs[m.indices.reshape(-1, 3)]
            count += int(np.count_nonzero(np.ptp(uv, axis=1).max(axis=1) > span))
    return count
