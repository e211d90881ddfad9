"""Coarser LODs made at load for a character whose file gives none (no mesh with lod > 0).

Each mesh (every piece, every variation choice) is simplified on its own by ``crowd.asset.simplify``, in
the bind pose and frames of the character's clips at once, and measured as it goes: a ladder of meshes,
each ``LADDER`` times the triangles of the one before, with its distance from the source (``deviation``:
exact, both ways, in every sampled pose, in metres). LOD k is made by taking meshes down
their ladders, always the one whose next rung adds least error, until the character draws at most
``MAX_SHARE`` of LOD k - 1's triangles, and on while the next step stays within ``ERROR_BUDGETS[k - 1]``
of the character's size: so every mesh is about as far from its source as the others, and a small piece
that cannot lose triangles cheaply is left as it is. The chain stops where no mesh can go further.

Each generated LOD carries the largest error of its meshes, and the character the distance from which
that error is at most one pixel at the reference view (1920 x 1080, 45 degrees vertically: the demo's):
``Character.lod_distances``. Each generated vertex is a source vertex, copied whole (position, skin,
texture coordinates, colour, morph deltas; its normal the one of its point's that faces the new triangle
best, so flat shading stays flat): a generated mesh is a list of source vertices and its triangles, and
that is what the cache keeps, by crowd.cache's rule, under the user's cache folder /lods.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import re
from pathlib import Path

import numpy as np

from ..cache import CacheError, cache_dir, read_arrays, write_arrays
from .model import Character, SkinnedMesh
from .pose import global_matrices, sample_clip
from .deviation import Deviation, expand_runs
from .simplify import BORDER_WEIGHT, MIN_NORMAL_COS, Collapser, Welded, representatives, weld

FORMAT = 2  # the cache files' layout and the generator's rules; a change makes every older file a miss (2: exact errors)
COARSER_LODS = 3  # one a global lod_distances start (LOD1 to LOD3)
# Each LOD's largest error, as a share of the character's size (its bind pose's longest side): for a
# person 1.8 m tall 9, 27 and 72 mm, one pixel at the reference view from 12, 35 and 94 m.
ERROR_BUDGETS = (0.005, 0.015, 0.04)
# Each LOD draws at most this share of the triangles of the one before (where the collapse gets there),
# even where that costs more than its budget: its switch distance then comes from the larger error.
MAX_SHARE = 0.5
LADDER = 0.75  # each rung keeps this share of the triangles of the one before
FLOOR = 0.02  # no rung below this share of the source's triangles
POSES = 16  # the bind pose and at most this many less one frames of the clips
REFERENCE_HEIGHT_PX, REFERENCE_FOV_Y = 1080, 45.0


def switch_distance(error_m: float) -> float:
    """Metres from the camera past which `error_m` covers at most one pixel of the reference view."""
    return float(error_m) * REFERENCE_HEIGHT_PX / (2.0 * math.tan(math.radians(REFERENCE_FOV_Y) / 2.0))


def sample_skinning(character: Character) -> np.ndarray:
    """Skinning matrices (K, J, 4, 4): the bind pose (identity) and POSES - 1 frames of the character's
    clips (at phases k / n, n = (POSES - 1) / clips and at least 3; evenly picked where there are more)."""
    sk = character.skeleton
    per_clip = max(3, (POSES - 1) // max(len(character.clips), 1))
    frames = [(i, k / per_clip) for i in range(len(character.clips)) for k in range(per_clip)]
    if len(frames) > POSES - 1:
        frames = [frames[int(i)] for i in np.linspace(0, len(frames) - 1, POSES - 1).round()]
    out = [np.broadcast_to(np.eye(4), (1, sk.joint_count, 4, 4))]
    for clip in sorted({i for i, _ in frames}):  # each clip sampled once, at its picked phases
        phases = np.array([phase for i, phase in frames if i == clip])
        out.append(global_matrices(sk, sample_clip(sk, character.clips[clip], phases)) @ sk.inverse_bind[None])
    return np.concatenate(out)


def _skin(skinning: np.ndarray, positions: np.ndarray, joints: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Linear-blend skinned points (P, K, 3), float64."""
    pos = np.asarray(positions, np.float64)
    out = np.zeros((len(pos), skinning.shape[0], 3))
    for slot in range(joints.shape[1]):
        m = skinning[:, joints[:, slot]]  # (K, P, 4, 4)
        moved = np.einsum("kpij,pj->pki", m[..., :3, :3], pos) + np.transpose(m[..., :3, 3], (1, 0, 2))
        out += np.asarray(weights[:, slot], np.float64)[:, None, None] * moved
    return out


class _Chain:
    """One mesh's ladder: its welded vertices, its points in every pose, and the rungs the collapse reached."""

    def __init__(self, mesh: SkinnedMesh, skinning: np.ndarray):
        self.mesh = mesh
        self.welded: Welded = weld(mesh)
        w = self.welded
        point_vertex = np.unique(w.vertex_point, return_index=True)[1]
        first = w.source[point_vertex]
        posed = _skin(skinning, mesh.positions[first], mesh.joints[first], mesh.weights[first])
        low, high = (posed.reshape(-1, 3).min(axis=0), posed.reshape(-1, 3).max(axis=0)) if len(posed) else (np.zeros(3), np.zeros(3))
        extent = float(np.max(high - low))
        self.scale = extent if math.isfinite(extent) and extent > 0.0 else 1.0
        self.posed = (posed - 0.5 * (low + high)) / self.scale  # about unit size: the quadrics neither overflow nor vanish
        self.source_points = w.vertex_point[w.triangles]
        tri_wedges = w.vertex_wedge[w.triangles]
        source = len(tri_wedges)
        targets, t = [], source
        while source and int(t * LADDER) >= max(1, math.ceil(FLOOR * source)) and int(t * LADDER) < t:
            t = int(t * LADDER)
            targets.append(t)
        collapser = Collapser(self.posed, tri_wedges, w.wedge_point)
        reached = collapser.run(targets)
        self.collapses = collapser.collapses
        self.rungs = [(tri_wedges, 0)]
        for tris, done in reached:
            if 0 < len(tris) < len(self.rungs[-1][0]):  # a piece is never made to vanish
                self.rungs.append((tris, done))
        self._errors: dict[int, float] = {0: 0.0}
        self._deviation = Deviation(self.posed, self.source_points)

    def triangles(self, rung: int) -> int:
        return len(self.rungs[rung][0])

    def error(self, rung: int) -> float:
        """Rung `rung`'s distance from the source in metres (``deviation``), worked out once."""
        if rung not in self._errors:
            tris, done = self.rungs[rung]
            rep = representatives(len(self.posed), self.collapses[:done])
            self._errors[rung] = self._deviation.measure(self.welded.wedge_point[tris], rep) * self.scale
        return self._errors[rung]

    def lod_mesh(self, rung: int) -> tuple[np.ndarray, np.ndarray]:
        """Rung `rung` as (source vertex indices (V',) int64, triangles uint32 (3T',) over them): each
        corner the vertex of its wedge whose normal is nearest its triangle's."""
        w, mesh = self.welded, self.mesh
        tris = self.rungs[rung][0]
        points = w.wedge_point[tris]
        bind = self.posed[:, 0]
        face = np.cross(bind[points[:, 1]] - bind[points[:, 0]], bind[points[:, 2]] - bind[points[:, 0]])
        by_wedge = np.argsort(w.vertex_wedge, kind="stable")
        count = np.bincount(w.vertex_wedge, minlength=len(w.wedge_point))
        corners = tris.ravel()
        owner, at = expand_runs((np.cumsum(count) - count)[corners], count[corners])
        candidate = by_wedge[at]
        facing = np.einsum("nc,nc->n", np.asarray(mesh.normals, np.float64)[w.source[candidate]], face[owner // 3])
        # The best-facing candidate of each corner (the first of equals): sort by corner, then facing down.
        order = np.lexsort((-facing, owner))
        best = candidate[order[np.r_[0, np.flatnonzero(np.diff(owner[order])) + 1]]] if len(owner) else candidate
        used, local = np.unique(best, return_inverse=True)
        return w.source[used], local.astype(np.uint32)


def character_size(character: Character) -> float:
    """The longest side of the box of the character's LOD0 meshes at bind (1 where that is 0)."""
    pos = [np.asarray(m.positions, np.float64) for m in character.meshes if m.lod == 0 and len(m.positions)]
    if not pos:
        return 1.0
    allp = np.concatenate(pos)
    size = float(np.ptp(allp, axis=0).max())
    return size if math.isfinite(size) and size > 0.0 else 1.0


def generate(character: Character, skinning: np.ndarray | None = None) -> tuple[list[list[tuple[np.ndarray, np.ndarray]]], np.ndarray, list[str]]:
    """For each mesh, its coarser LODs (up to COARSER_LODS) as (source vertices, triangles), the error
    of each (meshes, LODs) in metres, and a line for each mesh that could not be simplified. Every mesh
    gets the same number of LODs; a mesh that stops early repeats its last. `skinning`: the character's
    ``sample_skinning``, where the caller has it already (the cache's key needs it too)."""
    skinning = sample_skinning(character) if skinning is None else skinning
    size = character_size(character)
    chains = [_Chain(m, skinning) for m in character.meshes]
    notes = [f"mesh {c.mesh.name!r}: its {c.triangles(0):,} triangles could not be simplified (each collapse would tear a seam "
             f"or a border, or fold a triangle); drawn whole at every LOD" for c in chains if len(c.rungs) == 1 and c.triangles(0)]
    chosen = [[0] for _ in chains]
    for budget in ERROR_BUDGETS[:COARSER_LODS]:
        rungs = [picks[-1] for picks in chosen]
        before = sum(c.triangles(r) for c, r in zip(chains, rungs))
        # Every mesh the same error where it can: the mesh whose next rung costs least goes first, until
        # the LOD draws at most MAX_SHARE of the triangles of the one before, and on while within budget.
        while True:
            movable = [i for i, (c, r) in enumerate(zip(chains, rungs)) if r + 1 < len(c.rungs)]
            if not movable:
                break
            small = sum(c.triangles(r) for c, r in zip(chains, rungs)) <= MAX_SHARE * before
            if len(movable) == 1 and not small:
                i = movable[0]  # the one way on: its error chooses nothing, so it is not measured (most of the time taken)
            else:
                error, i = min((chains[i].error(rungs[i] + 1), i) for i in movable)
                if small and error > budget * size:
                    break
            rungs[i] += 1
        if sum(c.triangles(r) for c, r in zip(chains, rungs)) >= before:
            break
        for picks, rung in zip(chosen, rungs):
            picks.append(rung)
    lods = [[c.lod_mesh(r) for r in picks[1:]] for c, picks in zip(chains, chosen)]
    errors = np.array([[c.error(r) for r in picks[1:]] for c, picks in zip(chains, chosen)], np.float64).reshape(len(chains), -1)
    return lods, errors, notes


def lod_distances(errors: np.ndarray) -> tuple[float, ...]:
    """Each LOD's switch distance from its meshes' largest error (``switch_distance``), made strictly
    ascending (a LOD no worse than the one before starts a millimetre after it)."""
    out: list[float] = []
    for error in errors.max(axis=0) if errors.size else ():
        d = max(switch_distance(error), 1e-3)
        # (past 1e13 m a millimetre is below float64's step: the next float up, then)
        out.append(max(d, out[-1] + 1e-3, float(np.nextafter(out[-1], np.inf))) if out else d)
    return tuple(out)


def _key(character: Character, skinning: np.ndarray) -> str:
    h = hashlib.sha256(f"crowd lods {FORMAT} {COARSER_LODS} {ERROR_BUDGETS} {LADDER} {FLOOR} {POSES} {BORDER_WEIGHT} {MIN_NORMAL_COS}".encode())
    for m in character.meshes:
        h.update(f"{m.name} {m.lod} {m.morph_count}".encode())
        for a in (m.positions, m.normals, m.joints, m.weights, m.indices, m.colors, m.uvs, m.morph_positions, m.morph_normals):
            h.update(b"-" if a is None else np.ascontiguousarray(a).tobytes())
    h.update(np.ascontiguousarray(skinning).tobytes())
    return h.hexdigest()[:32]


def _to_arrays(key: str, lods, errors) -> dict[str, np.ndarray]:
    arrays = {"key": np.array(key), "errors": errors}
    for i, chain in enumerate(lods):
        for k, (vertices, indices) in enumerate(chain):
            arrays[f"mesh{i}_lod{k + 1}_vertices"] = vertices
            arrays[f"mesh{i}_lod{k + 1}_indices"] = indices
    return arrays


def _from_arrays(path: Path, key: str, arrays: dict[str, np.ndarray], meshes: list[SkinnedMesh]):
    """The LODs a checked cache file holds, each checked against its mesh; CacheError (one line) otherwise."""
    if str(arrays.get("key", "")) != key:
        raise CacheError(f"{path}: was made for another character (a copied or renamed file)")
    errors = arrays.get("errors")
    if errors is None or errors.dtype != np.float64 or errors.ndim != 2 or errors.shape[0] != len(meshes) \
            or errors.shape[1] > COARSER_LODS or not np.all(np.isfinite(errors)) or np.any(errors < 0):
        raise CacheError(f"{path}: its errors do not fit the character's {len(meshes)} meshes")
    lods = []
    for i, mesh in enumerate(meshes):
        chain = []
        for k in range(1, errors.shape[1] + 1):
            vertices, indices = arrays.get(f"mesh{i}_lod{k}_vertices"), arrays.get(f"mesh{i}_lod{k}_indices")
            if vertices is None or indices is None or vertices.dtype != np.int64 or indices.dtype != np.uint32 or vertices.ndim != 1 \
                    or indices.ndim != 1 or indices.size % 3 or (vertices.size and (vertices.min() < 0 or vertices.max() >= len(mesh.positions))) \
                    or (indices.size and int(indices.max()) >= vertices.size):
                raise CacheError(f"{path}: mesh {i} LOD{k} does not fit mesh {mesh.name!r}")
            chain.append((vertices, indices))
        lods.append(chain)
    if len(arrays) != 2 + 2 * len(meshes) * errors.shape[1]:
        raise CacheError(f"{path}: holds arrays of another character")
    return lods, errors


def lod_mesh(mesh: SkinnedMesh, lod: int, vertices: np.ndarray, indices: np.ndarray) -> SkinnedMesh:
    """`mesh`'s vertices `vertices` (copied whole) drawn as triangles `indices`: its LOD `lod`."""
    def take(a):
        return None if a is None else np.ascontiguousarray(a[vertices])

    morphs = {} if not mesh.morph_count else dict(
        morph_targets=mesh.morph_targets.copy(), morph_positions=np.ascontiguousarray(mesh.morph_positions[:, vertices]),
        morph_normals=np.ascontiguousarray(mesh.morph_normals[:, vertices]))
    return dataclasses.replace(mesh, name=f"{mesh.name}_lod{lod}", lod=lod, positions=take(mesh.positions), normals=take(mesh.normals),
                               joints=take(mesh.joints), weights=take(mesh.weights), indices=np.asarray(indices, np.uint32).copy(),
                               colors=take(mesh.colors), uvs=take(mesh.uvs), **morphs)


def with_generated_lods(character: Character, cache: bool = True, folder: Path | None = None) -> Character:
    """`character` with coarser LODs made for it where its file gives none (no mesh with lod > 0), and
    ``lod_distances`` from their errors; unchanged otherwise. With `cache`, the LODs are read from (or
    written to) `folder` (default: crowd.cache's "lods" folder); a file that does not read or check is
    rebuilt, with one line in the character's warnings."""
    if not character.meshes or any(m.lod > 0 for m in character.meshes):
        return character
    warnings = list(character.warnings)
    path = None
    found = None
    skinning = sample_skinning(character)
    if cache:
        name = re.sub(r"[^A-Za-z0-9_.-]", "_", character.name)[:48] or "character"
        key = _key(character, skinning)
        path = (folder or cache_dir("lods")) / f"{name}-lods-{key}.npz"
        if path.exists():
            try:
                found = _from_arrays(path, key, read_arrays(path), character.meshes)
            except CacheError as exc:
                warnings.append(f"LOD cache rebuilt: {exc}")
    if found is None:
        lods, errors, notes = generate(character, skinning)
        warnings += notes
        if path is not None:
            try:
                write_arrays(path, _to_arrays(key, lods, errors))
            except OSError as exc:
                warnings.append(f"LOD cache not written ({path}: {exc.strerror or exc})")
    else:
        lods, errors = found
    if not errors.shape[1]:
        warnings.append("no coarser LOD made: no mesh could be simplified")
        return dataclasses.replace(character, warnings=warnings)
    meshes = list(character.meshes)
    for k in range(errors.shape[1]):
        meshes += [lod_mesh(m, k + 1, *chain[k]) for m, chain in zip(character.meshes, lods)]
    distances = lod_distances(errors)
    counts = [sum(m.triangle_count for m in meshes if m.lod == k) for k in range(errors.shape[1] + 1)]
    warnings.append(f"LODs 1 to {errors.shape[1]} made (none in the file): {' / '.join(f'{c:,}' for c in counts)} triangles over every "
                    f"piece, from {' / '.join(f'{d:.3g}' for d in distances)} m (an error of 1 pixel at {REFERENCE_HEIGHT_PX} px, "
                    f"{REFERENCE_FOV_Y:g} degrees)")
    return dataclasses.replace(character, meshes=meshes, warnings=warnings, lod_distances=distances).validate()
