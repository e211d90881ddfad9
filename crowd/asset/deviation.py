"""How far a simplified mesh lies from its source: the error behind each generated LOD's switch distance
(crowd.asset.lod).

The measure (``Deviation.measure``) is the larger of both ways, in every sampled pose:
- each source point's distance to the simplified surface;
- each simplified triangle's centre's distance to the source surface.
It is exact: what a search of every triangle finds, to the last bit (tests/test_generated_lods.py checks
it against one).

How, in about linear time. An upper bound first, for every (point, pose) and (centre, pose): the
distance to one triangle, picked at bind as the nearest of those near it in the meshes' connectivity (a
source point: the simplified triangles around the point it ended on; a centre: the source triangles
around the points its corners took in; where there are none, the nearest at bind from the grid). Then
exact distances (``TriangleGrid``, a uniform grid of a pose's triangles; or every pair, where there are
few), in descending order of bound, until no bound left is above the largest exact distance found:
nothing below can change the answer. The bound is close for most (the collapse moves the surface near
the points it moves, and a surface moves about rigidly near a point), so few are searched; where it is
loose, the search finds the truth. The measure before this one (a bound from the connectivity alone)
read 93 mm for a CesiumMan rung that lies 1.1 mm from its source.
"""

from __future__ import annotations

import numpy as np

# A grid's cells are made coarser (twice the side) while its triangles would be listed under more than
# this many cells each on average: a few large triangles must not fill memory with cell entries.
GRID_LOAD = 8
# A grid has at most this many cells along its longest side: keys stay small, and a far-off stray
# triangle cannot make a grid of billions of cells.
GRID_CELLS = 2048
# Triangles whose box is within this of a search box are searched too: covers rounding in distances of
# coordinates about 1 in size (the collapse's normalised units), so a search never misses the nearest.
MARGIN = 1e-9
BRUTE = 1 << 13  # point-triangle pairs below which a search tries every pair rather than build a grid
CHUNK = 1 << 21  # (query, cell) or (query, triangle) pairs handled at once: tens of MB


def point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Distance (N,) from points p to triangles abc (each (N, 3)): to the plane where p projects inside
    the triangle, else to the nearest edge (a degenerate triangle is its edges)."""
    return _distance_rows(*(np.ascontiguousarray(np.asarray(v, np.float64).T) for v in (p, a, b, c)))


def _distance_rows(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``point_triangle_distance`` on coordinates as rows (3, N): the layout numpy runs fastest, which
    counts, as this is most of the time LODs take to measure."""

    def cross(u, v):
        return u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]

    def dot(u, v):
        return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]

    n = cross(b - a, c - a)
    nn = dot(n, n)
    # A triangle too thin for its normal to be worked out is its edges: a plane through it would be
    # a guess, and the distance to a plane is never more than to the triangle (a guess could undercut).
    inside = nn > 1e-30
    for s, e in ((a, b), (b, c), (c, a)):
        inside &= dot(cross(e - s, p - s), n) >= 0.0
    plane = np.abs(dot(p - a, n)) / np.sqrt(np.maximum(nn, 1e-30))

    def segment(s, e):
        d, w = e - s, p - s
        t = np.clip(dot(w, d) / np.maximum(dot(d, d), 1e-30), 0.0, 1.0)
        r = w - t * d
        return dot(r, r)

    edges = np.sqrt(np.minimum(np.minimum(segment(a, b), segment(b, c)), segment(c, a)))
    return np.where(inside, plane, edges)


def incidence(tri_points: np.ndarray, point_count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each point's triangles: (first, count) per point into the returned triangle list."""
    corners = tri_points.ravel()
    order = np.argsort(corners, kind="stable")
    count = np.bincount(corners, minlength=point_count)
    return np.cumsum(count) - count, count, order // 3


def expand_runs(first: np.ndarray, count: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(owner, position) for every item of the runs [first, first + count), owner by owner."""
    owner = np.repeat(np.arange(len(count)), count)
    return owner, np.repeat(first - (np.cumsum(count) - count), count) + np.arange(int(count.sum()))


def distinct(keys: np.ndarray) -> np.ndarray:
    """The distinct values of int64 `keys`, ascending: ``np.unique``'s answer, several times faster on
    the hundreds of thousands of pair keys a rung makes (numpy 2's hashing unique is slow on them)."""
    keys = np.sort(keys)
    return keys[np.r_[True, keys[1:] != keys[:-1]]] if len(keys) else keys


def least(distance: np.ndarray, owner: np.ndarray, n: int) -> np.ndarray:
    """Each of `n` owners' least distance (inf for an owner with none); `owner` (one a distance) ascending."""
    out = np.full(n, np.inf)
    if len(owner):
        starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
        out[owner[starts]] = np.minimum.reduceat(distance, starts)
    return out


class TriangleGrid:
    """Triangles `triangles` (T, 3) of points `vertices` (P, 3), each listed under every cell of a uniform
    grid that its bounding box overlaps. ``nearest`` finds each query point's exact distance to them."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray):
        self.vertices = vertices
        self.triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
        a, b, c = (vertices[self.triangles[:, i]] for i in range(3))
        self.lo, self.hi = np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)  # (numpy reduces a short axis slowly)
        self.origin = self.lo.min(axis=0)
        extent = float((self.hi.max(axis=0) - self.origin).max())
        # Cells about the size of a triangle (the median box's longest side): a point's neighbourhood is
        # a few cells of a few triangles.
        size = self.hi - self.lo
        size = np.maximum(np.maximum(size[:, 0], size[:, 1]), size[:, 2])
        self.h = max(float(np.partition(size, len(size) // 2)[len(size) // 2]), extent / GRID_CELLS, 1e-12)
        while True:
            first, last = self._cell(self.lo), self._cell(self.hi)
            spans = last - first + 1
            entries = np.prod(spans, axis=1)
            if entries.sum() <= GRID_LOAD * len(entries):
                break
            self.h *= 2.0
        self.shape = last.max(axis=0) + 1  # cells along x, y, z
        tri, at = expand_runs(np.zeros(len(entries), np.int64), entries)
        keys = self._key(first[tri] + _unravel(at, spans[tri]))
        order = np.argsort(keys, kind="stable")  # by cell, each cell's triangles ascending
        keys = keys[order]
        start = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
        self.keys, self.start, self.count = keys[start], start, np.diff(np.r_[start, len(keys)])
        self.listed = tri[order]

    def _cell(self, x: np.ndarray) -> np.ndarray:
        """The cell (N, 3) int64 of coordinates `x` (N, 3)."""
        return np.floor((x - self.origin) / self.h).astype(np.int64)

    def _key(self, cells: np.ndarray) -> np.ndarray:
        nx, ny = int(self.shape[0]), int(self.shape[1])
        return (cells[:, 2] * ny + cells[:, 1]) * nx + cells[:, 0]

    def nearest(self, points: np.ndarray, bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact distance (Q,) from each of `points` (Q, 3) to the triangles, and which triangle is
        nearest (the first of equals), given that the distance is at most `bound` (Q,; inf where nothing
        is known). Each search takes the triangles whose box is within a radius of the point: first a
        cell's side (or the bound), and where the least found is past the radius, that least (every
        nearer triangle is then within it); a search that finds nothing doubles its radius."""
        out, which = np.full(len(points), np.inf), np.full(len(points), -1)
        radius = np.minimum(bound, self.h)
        todo = np.arange(len(points))
        while len(todo):
            found, tri = self._least_within(points[todo], radius[todo])
            done = (found <= radius[todo]) | (radius[todo] >= bound[todo])
            out[todo[done]], which[todo[done]] = found[done], tri[done]
            rest, found = todo[~done], found[~done]
            radius[rest] = np.where(np.isfinite(found), np.minimum(found, bound[rest]), 2.0 * radius[rest])
            todo = rest
        return out, which

    def _least_within(self, points: np.ndarray, radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The least distance from each point to the triangles whose box meets the cube of half-side
        `radius` (+ MARGIN) around it, and that triangle; inf and -1 where there is none."""
        lo_cell = np.maximum(self._cell(points - (radius + MARGIN)[:, None]), 0)
        hi_cell = np.minimum(self._cell(points + (radius + MARGIN)[:, None]), self.shape - 1)
        spans = np.maximum(hi_cell - lo_cell + 1, 0)
        cells = np.prod(spans, axis=1)
        # A search box of more cells than there are triangles tests every triangle's box instead.
        wide = cells > len(self.triangles)
        cost = np.where(wide, len(self.triangles), cells)
        out, which = np.empty(len(points)), np.empty(len(points), np.int64)
        bounds = np.r_[0, np.flatnonzero(np.diff(np.cumsum(cost) // CHUNK)) + 1, len(points)]
        for s, e in zip(bounds[:-1], bounds[1:]):
            query, tri = self._candidates(points[s:e], radius[s:e], lo_cell[s:e], spans[s:e], cells[s:e], wide[s:e])
            corner = [np.ascontiguousarray(self.vertices[self.triangles[tri, i]].T) for i in range(3)]
            best, out[s:e] = nearest_candidate(_distance_rows(np.ascontiguousarray(points[s:e][query].T), *corner), query, e - s)
            which[s:e] = np.where(best >= 0, tri[np.maximum(best, 0)], -1) if len(tri) else -1
        return out, which

    def _candidates(self, points, radius, lo_cell, spans, cells, wide):
        """(query, triangle) pairs, each once, sorted by query, of the triangles that may be within
        `radius` of each query point."""
        t = len(self.triangles)
        narrow = np.flatnonzero(~wide)
        owner, at = expand_runs(np.zeros(len(narrow), np.int64), cells[narrow])
        keys = self._key(lo_cell[narrow][owner] + _unravel(at, spans[narrow][owner]))
        slot = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
        hit = self.keys[slot] == keys
        cell_owner, cell_at = expand_runs(self.start[slot[hit]], self.count[slot[hit]])
        pairs = [narrow[owner[hit]][cell_owner] * t + self.listed[cell_at]]
        for w in np.flatnonzero(wide):  # every triangle whose box meets the search box
            r = radius[w] + MARGIN
            pairs.append(w * t + np.flatnonzero(np.all((self.lo <= points[w] + r) & (self.hi >= points[w] - r), axis=1)))
        pairs = distinct(np.concatenate(pairs))
        return pairs // t, pairs % t


def _unravel(at: np.ndarray, spans: np.ndarray) -> np.ndarray:
    """Offsets (N, 3) of the `at`-th cell (x fastest) of boxes `spans` (N, 3) cells wide."""
    x = at % spans[:, 0]
    rest = at // spans[:, 0]
    return np.stack([x, rest % spans[:, 1], rest // spans[:, 1]], axis=1)


class Deviation:
    """The distance of simplified versions of one mesh (its rungs) from it (``measure``). `posed`
    (P, K, 3) float64 is each point in each of K poses, `source` (T, 3) the mesh's triangles as points;
    the source's grids (one a pose, made when first searched) serve every rung."""

    def __init__(self, posed: np.ndarray, source: np.ndarray):
        self.posed = np.asarray(posed, np.float64)
        self.source = np.asarray(source, np.int64).reshape(-1, 3)
        self.used = distinct(self.source.ravel())
        self.rows = np.ascontiguousarray(np.transpose(self.posed, (1, 2, 0)))  # (K, 3, P): the layout _distance_rows wants
        self.src_first, self.src_count, self.src_tris = incidence(self.source, self.posed.shape[0])
        self._grids: dict[int, TriangleGrid] = {}
        self.searched = 0  # (point or centre, pose) pairs the last measure worked out exactly

    def measure(self, simplified: np.ndarray, rep: np.ndarray) -> float:
        """How far `simplified` (triangles (T', 3) of points) lies from the source, the larger of both
        ways over every pose (see the module docstring); `rep` is each point's end in the collapse (the
        point it ended on, itself where it stayed)."""
        posed, source, used = self.posed, self.source, self.used
        p, k = posed.shape[:2]
        simplified = np.asarray(simplified, np.int64).reshape(-1, 3)
        self.searched = 0
        if not len(source) or not len(simplified):
            return 0.0 if not len(source) else float(np.linalg.norm(posed - posed[rep], axis=-1).max())
        # The bounds' candidates: each source point with the simplified triangles around its end ...
        first, count, tris = incidence(simplified, p)
        a_owner, at = expand_runs(first[rep[used]], count[rep[used]])
        a_point, a_tri = used[a_owner], simplified[tris[at]]
        # ... each simplified triangle with the source triangles around the points its corners took in.
        members = np.argsort(rep, kind="stable")
        member_count = np.bincount(rep, minlength=p)
        corner_owner, corner_at = expand_runs((np.cumsum(member_count) - member_count)[simplified.ravel()], member_count[simplified.ravel()])
        point = members[corner_at]
        tri_owner, tri_at = expand_runs(self.src_first[point], self.src_count[point])
        found = distinct((corner_owner[tri_owner] // 3) * len(source) + self.src_tris[tri_at])  # each pair once
        b_owner, b_tri = found // len(source), source[found % len(source)]
        # Every candidate in the bind pose, and in the others only the one nearest at bind: the surface
        # moves about rigidly near a point, so it stays about as near, and the bounds cost a sixteenth.
        simplified_grids: dict[int, TriangleGrid] = {}
        bind = self.rows[0]
        centres = (bind[:, simplified[:, 0]] + bind[:, simplified[:, 1]] + bind[:, simplified[:, 2]]) / 3.0
        a_best, a_bound = nearest_candidate(_distance_rows(bind[:, a_point], *(bind[:, a_tri[:, i]] for i in range(3))), a_owner, len(used))
        b_best, b_bound = nearest_candidate(_distance_rows(centres[:, b_owner], *(bind[:, b_tri[:, i]] for i in range(3))), b_owner, len(simplified))
        a_tri, b_tri = a_tri[a_best], b_tri[b_best]
        # A point whose end lost every triangle (a small part collapsed to nothing) has no candidate: its
        # nearest triangle at bind, from the grid, serves instead.
        lost = np.flatnonzero(a_best < 0)
        if len(lost):
            simplified_grids[0] = TriangleGrid(posed[:, 0], simplified)
            a_bound[lost], nearest = simplified_grids[0].nearest(posed[used[lost], 0], np.full(len(lost), np.inf))
            a_tri[lost] = simplified[nearest]
        lost = np.flatnonzero(b_best < 0)
        if len(lost):
            self._grids[0] = self._grids.get(0) or TriangleGrid(posed[:, 0], source)
            b_bound[lost], nearest = self._grids[0].nearest(centres[:, lost].T, np.full(len(lost), np.inf))
            b_tri[lost] = source[nearest]
        n_a, n_b = len(used), len(simplified)
        bounds = np.empty((2, k), object)
        bounds[0, 0], bounds[1, 0] = a_bound, b_bound
        for pose in range(1, k):
            x = self.rows[pose]
            bounds[0, pose] = _distance_rows(x[:, used], *(x[:, a_tri[:, i]] for i in range(3)))
            centres = (x[:, simplified[:, 0]] + x[:, simplified[:, 1]] + x[:, simplified[:, 2]]) / 3.0
            bounds[1, pose] = _distance_rows(centres, *(x[:, b_tri[:, i]] for i in range(3)))
        bounds = np.concatenate([*bounds[0], *bounds[1]])  # the source points pose by pose, then the centres
        # Exact distances, largest bound first, in batches that double, while a bound is above the largest found.
        order = np.argsort(-bounds, kind="stable")
        worst, start, size = 0.0, 0, 64
        while start < len(order) and bounds[order[start]] > worst:
            take = order[start:start + size]
            take = take[bounds[take] > worst]
            start, size = start + size, 2 * size
            self.searched += len(take)
            of_points = take < n_a * k
            a_pose, j = np.divmod(take[of_points], n_a)
            b_pose, t = np.divmod(take[~of_points] - n_a * k, n_b)
            for pose in range(k):
                mine = a_pose == pose
                if np.any(mine):
                    found = _exact(simplified_grids, pose, posed[:, pose], simplified, posed[used[j[mine]], pose], bounds[take[of_points][mine]])
                    worst = max(worst, float(found.max()))
                mine = b_pose == pose
                if np.any(mine):
                    c = posed[simplified[t[mine]], pose]  # (n, 3, 3)
                    found = _exact(self._grids, pose, posed[:, pose], source, (c[:, 0] + c[:, 1] + c[:, 2]) / 3.0, bounds[take[~of_points]][mine])
                    worst = max(worst, float(found.max()))
        return worst


def _exact(grids: dict[int, TriangleGrid], pose: int, vertices: np.ndarray, triangles: np.ndarray, points: np.ndarray,
           bound: np.ndarray) -> np.ndarray:
    """Exact distances from `points` to `triangles` of `vertices` (pose `pose`): every pair where they
    are few (a grid costs more to build than that), else through the pose's grid in `grids`, made once."""
    if pose not in grids and len(points) * len(triangles) <= BRUTE:
        owner = np.repeat(np.arange(len(points)), len(triangles))
        tri = np.tile(triangles, (len(points), 1))
        return least(_distance_rows(np.ascontiguousarray(points[owner].T), *(np.ascontiguousarray(vertices[tri[:, i]].T) for i in range(3))),
                     owner, len(points))
    if pose not in grids:
        grids[pose] = TriangleGrid(vertices, triangles)
    return grids[pose].nearest(points, bound)[0]


def nearest_candidate(distance: np.ndarray, owner: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """For each of `n` owners, the index of its nearest candidate (the first of equals; -1 where it has
    none) and that distance (inf where none); `owner` (one a candidate) ascending."""
    best = least(distance, owner, n)
    at = np.flatnonzero(distance == best[owner])
    first = at[np.r_[True, owner[at][1:] != owner[at][:-1]]] if len(at) else at
    index = np.full(n, -1)
    index[owner[first]] = first
    return index, best


def deviation(posed: np.ndarray, source: np.ndarray, simplified: np.ndarray, rep: np.ndarray) -> float:
    """``Deviation(posed, source).measure(simplified, rep)``: one rung's distance from its source."""
    return Deviation(posed, source).measure(simplified, rep)
