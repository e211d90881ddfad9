"""Quadric half-edge collapse of a skinned mesh, measured in several poses at once: the simplifier behind
the coarser LODs made for imported characters (``crowd.asset.lod``).

The mesh comes in as three nested kinds of vertex (``weld``):
- a *point* is where a vertex goes in any pose: position, skin and morph position deltas. Two vertices at
  one position with different skins part when the character moves, so they are two points;
- a *wedge* is a point with the attributes a seam must keep apart: texture coordinates and colour;
- a *vertex* is a wedge with its normal (and morph normal deltas): flat shading gives a point many.

The collapse works on points. Each step moves a point `u` onto a neighbour `v` (a half-edge collapse: no
vertex is created or moved, so every kept vertex keeps its own skin, texture coordinates and morph deltas,
which stay consistent with its position by construction). The cost of a step is the quadric error
(Garland and Heckbert 1997) of `v`'s position summed over the poses (the bind pose and frames of the
character's clips): a step that looks free at bind but stretches a triangle across a bending joint costs
what it does in the frames where the joint bends. A step is refused when it would
- join two wedges of `u` into one, or leave one without a partner (a texture seam or a colour border
  would tear or smear): `u`'s wedges must map one to one onto `v`'s through the triangles on the edge;
- pull a border point off its border (a border or seam edge also carries a plane that keeps it straight);
- change the topology (the link condition), or turn a triangle over in any pose.

Why by hand: the simplifiers with wheels (fast-simplification, pyfqmr) move vertices to new positions and
know nothing of seams or skins; meshoptimizer knows seams but has no wheel. docs/BENCHMARKS.md ("LODs for
imported characters") has the measured comparison.
"""

from __future__ import annotations

import heapq
from collections import Counter
from dataclasses import dataclass

import numpy as np

# A border or seam edge's plane weighs this much more than a face of the same size: enough that a border
# stays where it is unless moving it costs nothing.
BORDER_WEIGHT = 10.0
# A step is refused when a triangle it moves turns by more than this in any pose (cosine of 78 degrees).
MIN_NORMAL_COS = 0.2


@dataclass
class Welded:
    """A mesh's vertices welded three ways (see the module docstring); every array indexes the next."""

    source: np.ndarray  # int64 (V,): each vertex's first index in the mesh
    vertex_wedge: np.ndarray  # int64 (V,)
    wedge_point: np.ndarray  # int64 (W,)
    triangles: np.ndarray  # int64 (T, 3) of vertices, each on three distinct points
    dropped: int  # source triangles on fewer than three distinct points (they cover nothing)

    @property
    def vertex_point(self) -> np.ndarray:
        return self.wedge_point[self.vertex_wedge]

    @property
    def point_count(self) -> int:
        return int(self.wedge_point.max()) + 1 if self.wedge_point.size else 0


def _rows(arrays: list[np.ndarray], n: int) -> np.ndarray:
    """One opaque row per vertex of the raw bytes of `arrays` (each (n, ...)): rows equal in every bit."""
    parts = [np.ascontiguousarray(a).reshape(n, int(np.prod(a.shape[1:]))).view(np.uint8) for a in arrays]
    joined = np.ascontiguousarray(np.concatenate(parts, axis=1) if parts else np.zeros((n, 0), np.uint8))
    return joined.view(np.dtype((np.void, joined.shape[1]))).ravel() if joined.shape[1] else np.zeros(n, np.int8)


def _plain(a: np.ndarray) -> np.ndarray:
    """Floats with -0.0 made 0.0, so that equal values weld whatever their sign bit."""
    return np.asarray(a) + np.zeros((), np.asarray(a).dtype)


def canonical_skin(joints: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """A vertex's influences as one uint64 per slot, sorted: equal rows skin alike whatever the slot order,
    and a slot of weight 0 counts the same whatever joint it names."""
    w = _plain(np.asarray(weights, np.float32))
    j = np.where(w > 0.0, np.asarray(joints, np.uint64), np.uint64(0))
    return np.sort((j << np.uint64(32)) | w.view(np.uint32).astype(np.uint64), axis=1)


def weld(mesh) -> Welded:
    """`mesh`'s (a SkinnedMesh) vertices welded into vertices, wedges and points."""
    n = len(mesh.positions)
    morph = [] if not mesh.morph_count else [np.transpose(_plain(mesh.morph_positions), (1, 0, 2))]
    morph_normals = [] if not mesh.morph_count else [np.transpose(_plain(mesh.morph_normals), (1, 0, 2))]
    point_keys = [_plain(mesh.positions), canonical_skin(mesh.joints, mesh.weights), *morph]
    wedge_keys = point_keys + [_plain(a) for a in (mesh.uvs, mesh.colors) if a is not None]
    vertex_keys = wedge_keys + [_plain(mesh.normals), *morph_normals]
    _, source, vertex_of = np.unique(_rows(vertex_keys, n), return_index=True, return_inverse=True)
    _, first_wedge, vertex_wedge = np.unique(_rows([a[source] for a in wedge_keys], len(source)), return_index=True, return_inverse=True)
    _, wedge_point = np.unique(_rows([a[source[first_wedge]] for a in point_keys], len(first_wedge)), return_inverse=True)
    triangles = vertex_of.ravel()[np.asarray(mesh.indices, np.int64)].reshape(-1, 3)
    points = wedge_point[vertex_wedge[triangles]]
    distinct = (points[:, 0] != points[:, 1]) & (points[:, 1] != points[:, 2]) & (points[:, 0] != points[:, 2])
    return Welded(source.astype(np.int64), vertex_wedge.ravel().astype(np.int64), wedge_point.ravel().astype(np.int64),
                  triangles[distinct], int(np.count_nonzero(~distinct)))


# -- quadrics: the 10 distinct entries of the symmetric 4 x 4 matrix of a plane n.x + d = 0


def plane_quadrics(normal: np.ndarray, d: np.ndarray, weight: np.ndarray) -> np.ndarray:
    a, b, c = normal[..., 0], normal[..., 1], normal[..., 2]
    return weight[..., None] * np.stack([a * a, a * b, a * c, a * d, b * b, b * c, b * d, c * c, c * d, d * d], axis=-1)


def quadric_error(q: np.ndarray, x: np.ndarray) -> np.ndarray:
    """x^T Q x for quadrics q (..., 10) at points x (..., 3)."""
    px, py, pz = x[..., 0], x[..., 1], x[..., 2]
    return (q[..., 0] * px * px + 2.0 * q[..., 1] * px * py + 2.0 * q[..., 2] * px * pz + 2.0 * q[..., 3] * px
            + q[..., 4] * py * py + 2.0 * q[..., 5] * py * pz + 2.0 * q[..., 6] * py
            + q[..., 7] * pz * pz + 2.0 * q[..., 8] * pz + q[..., 9])


def _edges(tri_points: np.ndarray, tri_wedges: np.ndarray):
    """Every edge once (E, 2) (lower point first), with whether it is a border (not two triangles) or a
    seam (two triangles that give an end point different wedges), and each triangle corner's edge."""
    t = len(tri_points)
    a = tri_points[:, [0, 1, 2]].ravel()
    b = tri_points[:, [1, 2, 0]].ravel()
    wa, wb = tri_wedges[:, [0, 1, 2]].ravel(), tri_wedges[:, [1, 2, 0]].ravel()
    swap = a > b
    lo, hi = np.where(swap, b, a), np.where(swap, a, b)
    wlo, whi = np.where(swap, wb, wa), np.where(swap, wa, wb)
    order = np.lexsort((np.arange(3 * t), hi, lo))
    lo, hi, wlo, whi = lo[order], hi[order], wlo[order], whi[order]
    start = np.flatnonzero(np.r_[True, (lo[1:] != lo[:-1]) | (hi[1:] != hi[:-1])])
    counts = np.diff(np.r_[start, len(lo)])
    edge_of = np.empty(3 * t, np.int64)
    edge_of[order] = np.repeat(np.arange(len(start)), counts)
    same_lo = np.minimum.reduceat(wlo, start) == np.maximum.reduceat(wlo, start)
    same_hi = np.minimum.reduceat(whi, start) == np.maximum.reduceat(whi, start)
    return np.stack([lo[start], hi[start]], axis=1), counts != 2, (counts == 2) & ~(same_lo & same_hi), edge_of.reshape(t, 3)


class Collapser:
    """The collapse of one mesh, run down to a list of triangle counts (``run``).

    `posed` (P, K, 3) float64 is each point in each of K poses (normalised: an extent of about 1, so
    costs neither overflow nor vanish); `tri_wedges` (T, 3) the triangles as wedges; `wedge_point` (W,).
    """

    def __init__(self, posed: np.ndarray, tri_wedges: np.ndarray, wedge_point: np.ndarray):
        self.posed = np.asarray(posed, np.float64)
        p = self.posed.shape[0]
        tri_wedges = np.asarray(tri_wedges, np.int64).reshape(-1, 3)
        tri_points = np.asarray(wedge_point, np.int64)[tri_wedges]
        self.tw = tri_wedges.tolist()
        self.tp = tri_points.tolist()
        self.alive = [True] * len(self.tw)
        self.triangles = len(self.tw)
        self.point_tris: list[set[int]] = [set() for _ in range(p)]
        for t, corners in enumerate(self.tp):
            for c in corners:
                self.point_tris[c].add(t)
        self.version = [0] * p
        self.collapses: list[tuple[int, int]] = []
        self.area = np.zeros(p)  # each point's triangles' area, summed over the poses
        self.q = np.zeros((p, self.posed.shape[1], 10))
        self.heap: list[tuple[float, int, int, int, int]] = []
        if len(tri_points):
            edges = self._quadrics(tri_points, tri_wedges)
            us = np.concatenate([edges[:, 0], edges[:, 1]])
            vs = np.concatenate([edges[:, 1], edges[:, 0]])
            self.heap = self._entries(us, vs)
            heapq.heapify(self.heap)

    def _quadrics(self, tri_points: np.ndarray, tri_wedges: np.ndarray) -> np.ndarray:
        """Each point's quadrics (faces, and its border and seam edges' planes) and area; returns the edges."""
        q = self.q
        a, b, c = (self.posed[tri_points[:, i]] for i in range(3))  # (T, K, 3)
        cross = np.cross(b - a, c - a)
        length = np.linalg.norm(cross, axis=-1)
        unit = cross / np.maximum(length, 1e-300)[..., None]
        faces = plane_quadrics(unit, -np.einsum("tkc,tkc->tk", unit, a), 0.5 * length)
        for i in range(3):
            np.add.at(q, tri_points[:, i], faces)
        for i in range(3):
            np.add.at(self.area, tri_points[:, i], 0.5 * length.sum(axis=1))
        # A plane through each border and seam edge, square to its triangle, keeps the edge where it is.
        edges, border, seam, edge_of = _edges(tri_points, tri_wedges)
        for i in range(3):
            fixed = border[edge_of[:, i]] | seam[edge_of[:, i]]
            if not np.any(fixed):
                continue
            s, e = tri_points[fixed, i], tri_points[fixed, (i + 1) % 3]
            along = self.posed[e] - self.posed[s]
            side = np.cross(along, unit[fixed])
            side_length = np.linalg.norm(side, axis=-1)
            side = side / np.maximum(side_length, 1e-300)[..., None]
            planes = plane_quadrics(side, -np.einsum("tkc,tkc->tk", side, self.posed[s]), BORDER_WEIGHT * np.einsum("tkc,tkc->tk", along, along))
            np.add.at(q, s, planes)
            np.add.at(q, e, planes)
        return edges

    def _entries(self, us: np.ndarray, vs: np.ndarray) -> list[tuple[float, int, int, int, int]]:
        """Heap entries (cost, u, v, u's version, v's version) of collapsing each of `us` onto `vs`."""
        # Per area, so that the cost is a squared distance: summed over area, a step that removes a small
        # feature (a finger) would look cheap however far it moves the surface.
        cost = quadric_error(self.q[us] + self.q[vs], self.posed[vs]).sum(axis=1) / np.maximum(self.area[us] + self.area[vs], 1e-300)
        version = self.version
        return [(c, u, v, version[u], version[v]) for c, u, v in zip(np.maximum(cost, 0.0).tolist(), us.tolist(), vs.tolist())]

    def _plan(self, u: int, v: int) -> dict[int, int] | None:
        """The wedge map of collapsing `u` onto `v`, or None where the step is refused."""
        tp, tw = self.tp, self.tw
        tu, tv = self.point_tris[u], self.point_tris[v]
        shared = tu & tv
        if not shared:
            return None
        around_u = Counter(p for t in tu for p in tp[t])
        around_v = {p for t in tv for p in tp[t]}
        opposite = {p for t in shared for p in tp[t]} - {u, v}
        if (set(around_u) & around_v) - {u, v} != opposite:  # the link condition: no fold, no pinch
            return None
        # On a border (an edge of u with one triangle, or more than two), u moves only along it.
        if len(shared) == 2 and any(n != u and count != 2 for n, count in around_u.items()):
            return None
        mapping: dict[int, int] = {}
        for t in sorted(shared):
            wu, wv = tw[t][tp[t].index(u)], tw[t][tp[t].index(v)]
            if mapping.setdefault(wu, wv) != wv:
                return None
        if len(set(mapping.values())) != len(mapping) or {tw[t][tp[t].index(u)] for t in tu} != set(mapping):
            return None
        moved = sorted(tu - shared)
        if moved:
            old = np.array([tp[t] for t in moved])
            new = np.where(old == u, v, old)
            n_old, n_new = self._normals(old), self._normals(new)
            dot = (n_old * n_new).sum(axis=0)
            old_sq, new_sq = (n_old * n_old).sum(axis=0), (n_new * n_new).sum(axis=0)
            if np.any((old_sq > 1e-36) & ((dot <= 0.0) | (dot * dot <= MIN_NORMAL_COS * MIN_NORMAL_COS * old_sq * new_sq))):
                return None
        return mapping

    def _normals(self, corners: np.ndarray) -> np.ndarray:
        """Unnormalised normals (3, M, K) of triangles `corners` (M, 3) in every pose."""
        a, b, c = (self.posed[corners[:, i]] for i in range(3))
        e, f = (b - a).transpose(2, 0, 1), (c - a).transpose(2, 0, 1)
        return np.stack([e[1] * f[2] - e[2] * f[1], e[2] * f[0] - e[0] * f[2], e[0] * f[1] - e[1] * f[0]])

    def _apply(self, u: int, v: int, mapping: dict[int, int]) -> None:
        tp, tw = self.tp, self.tw
        for t in sorted(self.point_tris[u] & self.point_tris[v]):
            self.alive[t] = False
            self.triangles -= 1
            for p in tp[t]:
                self.point_tris[p].discard(t)
        for t in sorted(self.point_tris[u]):
            i = tp[t].index(u)
            tp[t][i] = v
            tw[t][i] = mapping[tw[t][i]]
            self.point_tris[v].add(t)
        self.point_tris[u].clear()
        self.q[v] += self.q[u]
        self.area[v] += self.area[u]
        self.version[v] += 1
        self.version[u] += 1
        self.collapses.append((u, v))
        near = np.array(sorted({p for t in self.point_tris[v] for p in tp[t]} - {v}), np.int64)
        if len(near):
            mine = np.full(len(near), v, np.int64)
            for entry in self._entries(np.concatenate([near, mine]), np.concatenate([mine, near])):
                heapq.heappush(self.heap, entry)

    def current(self) -> np.ndarray:
        """The triangles left (int64 (T', 3) of wedges), in their source order."""
        return np.array([w for w, alive in zip(self.tw, self.alive) if alive], np.int64).reshape(-1, 3)

    def run(self, targets: list[int]) -> list[tuple[np.ndarray, int]]:
        """Collapses until each of `targets` (triangle counts, descending) is reached, or no step is left.
        Returns for each target reached the triangles left and how many collapses it took (the prefix
        of ``collapses`` that made it); a target that could not be reached is left out."""
        out = []
        pending = list(targets)
        heap, version = self.heap, self.version
        while pending and heap:
            while pending and self.triangles <= pending[0]:
                out.append((self.current(), len(self.collapses)))
                pending.pop(0)
            if not pending:
                break
            _, u, v, su, sv = heapq.heappop(heap)
            if version[u] != su or version[v] != sv:
                continue
            mapping = self._plan(u, v)
            if mapping is not None:
                self._apply(u, v, mapping)
        while pending and self.triangles <= pending[0]:
            out.append((self.current(), len(self.collapses)))
            pending.pop(0)
        return out


def representatives(point_count: int, collapses: list[tuple[int, int]]) -> np.ndarray:
    """For each point, the point it ended on after `collapses` (itself where it stayed)."""
    rep = np.arange(point_count)
    for u, v in reversed(collapses):
        rep[u] = rep[v]
    return rep
