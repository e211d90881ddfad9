"""LODs keep their morph targets (issue 23, point 3): a coarser mesh of a piece that came without the
targets its finer mesh has gets them from it, each vertex taking the deltas of the finer mesh's nearest
vertex in bind space.

Why nearest vertex: a coarser LOD made by an exporter's decimation keeps a subset of the finer mesh's
vertices, or vertices close to its surface; the nearest vertex's deltas are then exact or close, and
need no triangle lookup. Each transfer is one line in ``character.warnings`` with the farthest distance
a vertex had to look, so a LOD that does not lie on its finer mesh shows."""

from __future__ import annotations

import dataclasses

import numpy as np

from .model import Character, SkinnedMesh

CHUNK_PAIRS = 1 << 23  # distances worked out at once: 64 MB of float64


def nearest_vertices(source: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each of `points` (P, 3) the index of its nearest vertex of `source` (S, 3) and the distance."""
    src = np.asarray(source, np.float64)
    pts = np.asarray(points, np.float64)
    src_sq = np.sum(src * src, axis=1)
    index = np.empty(len(pts), np.int64)
    dist = np.empty(len(pts))
    step = max(1, CHUNK_PAIRS // max(len(src), 1))
    for first in range(0, len(pts), step):
        p = pts[first:first + step]
        d2 = src_sq[None, :] - 2.0 * (p @ src.T) + np.sum(p * p, axis=1)[:, None]  # a matrix product: fast
        k = np.argmin(d2, axis=1)
        index[first:first + step] = k
        dist[first:first + step] = np.linalg.norm(src[k] - p, axis=1)
    return index, dist


def transfer_targets(character: Character) -> Character:
    """`character` with every target-less coarser mesh of a piece given the targets of that piece's
    finest mesh that has some (one warning a mesh); unchanged where there is nothing to transfer."""
    if not character.morphs:
        return character
    finest: dict[str, SkinnedMesh] = {}
    for mesh in sorted(character.meshes, key=lambda m: m.lod):
        if mesh.morph_count and mesh.piece not in finest:
            finest[mesh.piece] = mesh
    meshes, warnings = [], list(character.warnings)
    for mesh in character.meshes:
        source = finest.get(mesh.piece)
        if mesh.morph_count or source is None or mesh.lod <= source.lod:
            meshes.append(mesh)
            continue
        near, dist = nearest_vertices(source.positions, mesh.positions)
        meshes.append(dataclasses.replace(mesh, morph_targets=source.morph_targets.copy(), morph_positions=source.morph_positions[:, near].copy(),
                                          morph_normals=source.morph_normals[:, near].copy()))
        warnings.append(f"mesh {mesh.name!r}: its {source.morph_count} morph targets taken from {source.name!r} (LOD{source.lod}) "
                        f"by nearest vertex (farthest {float(dist.max()) * 1e3:.3g} mm)")
    if len(warnings) == len(character.warnings):
        return character
    return dataclasses.replace(character, meshes=meshes, warnings=warnings).validate()
