"""Separation is a position correction, not a force: each substep removes at most the fraction
min(stiffness x h, 1) of each overlap and moves an agent at most half the separation radius, so a
stiffness x dt far above 1 stays bounded. Neighbours come from a uniform grid over the world (agents
sorted by cell), never from all pairs, and the pair list is reused across substeps until an agent has
moved far enough to invalidate it.
"""

from __future__ import annotations

import math

import numpy as np

from .agent_pool import SharedArrays
from .config import DYING, AIError
from .workers import P_SIDE

SEPARATION_CELL_CAP = 48  # neighbours considered per row of three cells (bounds the work when many agents pile up)
# Metres from a person's axis to the farthest point of its standing pose, arms out front included (the
# built-in zombie, brute and survivor stand at 0.33, 0.62 and 0.47 m): a character wider than this gets
# the separation radius times its footprint over this; a person, or anything smaller, the radius itself.
PERSON_FOOTPRINT = 0.65


def kind_radii(radius: float, motions) -> np.ndarray:
    """Each character's separation radius (float64, one per Motion): `radius` (the setting), times its
    footprint over PERSON_FOOTPRINT where that is over 1. Two agents keep the mean of theirs apart."""
    return float(radius) * np.maximum(1.0, np.array([m.footprint for m in motions], np.float64) / PERSON_FOOTPRINT)


class SeparationMixin:
    """CrowdAI's part that builds the neighbour lists and pushes overlapping agents apart."""

    def _push_range(self, lo: int, hi: int, gain: float):
        """Separation pushes of agents lo..hi, from everyone's positions (nothing is moved here: the apply
        phase moves them, after every range has read the positions). Both agents of a pair closer than
        the separation radius r move apart by half the overlap, times `gain` (min(stiffness x h, 1)),
        and no agent moves more than r / 2. Every agent, every substep, the think budget's included: a
        pile-up must come apart as fast as without it (its agents think rarely, but they do not overlap
        for longer).

        An agent's entries in its range's list are contiguous and in the grid's order, so its push is a
        sum over the same entries in the same order whichever range it is in. Returns (agents, push x,
        push z) for the pushed ones, or None."""
        radii = self._separation_radii()
        first, second = self._range_list
        if not first.size:
            return None
        dx, dz = self.x[first] - self.x[second], self.z[first] - self.z[second]
        dist2 = dx * dx + dz * dz
        # A pair keeps the mean of its two characters' radii apart (one character: the setting's radius).
        r = radii[0] if radii.size == 1 else 0.5 * (radii[self.kind[first]] + radii[self.kind[second]])
        # Agents that died since the list was built are skipped here rather than by a rebuild.
        close = np.flatnonzero((dist2 < r * r) & (self.state[first] < DYING) & (self.state[second] < DYING))
        if not close.size:
            return None
        r = r if radii.size == 1 else r[close]
        first, second = first[close], second[close]
        fx, fz = _overlap_push(first, second, dx[close], dz[close], np.sqrt(dist2[close]), r)
        local = first - lo  # sorted: the list is in agent order
        agents = local[np.flatnonzero(np.concatenate(([True], local[1:] != local[:-1])))]
        push_x = np.bincount(local, weights=fx, minlength=hi - lo)[agents]
        push_z = np.bincount(local, weights=fz, minlength=hi - lo)[agents]
        # Stiffness x h above 1 removes the whole overlap, never more; no agent moves more than half its radius.
        own = radii[0] if radii.size == 1 else radii[self.kind[agents + lo]]
        norm = np.sqrt(push_x * push_x + push_z * push_z) * gain
        gain = gain * np.minimum(1.0, 0.5 * own / np.maximum(norm, 1e-12))
        return agents + lo, push_x * gain, push_z * gain

    def _separation_radii(self) -> np.ndarray:
        """Each character's separation radius (kind_radii), one entry where all of them are the setting's."""
        radii = kind_radii(self.config.separation_radius, self.motions)
        return radii[:1] if np.all(radii == radii[0]) else radii

    def _prepare_lists(self, moved2: float) -> bool:
        """Whether the separation's neighbour lists are to be rebuilt in this substep's push phase, and if
        so the grid they are built from (here, for the whole crowd: one sort). Each range's list holds,
        for each of its living agents, every living agent closer than the separation radius r and others
        up to 2r away. The lists are kept across substeps (a Verlet list, as in molecular dynamics)
        until some agent has moved r / 2 from where it stood when they were built (`moved2`: the largest
        squared move, measured by the think phase): until then no pair can have closed from over 2r to
        under r, so the lists still hold every close pair. A build costs about seven substeps' use of
        them; agents move 1 to 7 cm per substep."""
        r = float(self._separation_radii().max())  # (the widest pair's: every list and cell holds it)
        if self._pairs and moved2 <= 0.25 * r * r:
            return False
        self._params[P_SIDE] = self._build_grid(2.0 * r)
        self._pairs = True
        self.pair_builds += 1
        return True

    def _build_grid(self, size: float) -> int:
        """Living agents sorted into a uniform grid of `size`-wide cells (so every pair closer than `size`
        is in the same or adjacent cells): each one's cell, the agents in cell order and where each
        cell's agents start in it. Returns the grid's side in cells."""
        live = np.flatnonzero(self.state < DYING)
        everyone = live.size == self.n  # the usual case: plain arrays instead of gathers
        x, z = (self.x, self.z) if everyone else (self.x[live], self.z[live])
        size, side = grid_shape(self.half_extent, size, self.n)
        gx = np.minimum(np.maximum((x - (self.origin[0] - self.half_extent)) * (1.0 / size) + 1.0, 1.0), side - 2.0)
        gz = np.minimum(np.maximum((z - (self.origin[1] - self.half_extent)) * (1.0 / size) + 1.0, 1.0), side - 2.0)
        cell = gz.astype(np.int64) * side + gx.astype(np.int64)
        self._cell[live] = cell
        order = _sort_cells(cell, side * side)
        self._cell_order[: live.size] = order if everyone else live[order]
        cells = side * side + 1
        if self._pool is None:
            self._cell_first = np.zeros(cells, np.int64)
        else:
            if self._grid_block is None or self._grid_block.arrays["first"].size < cells:
                if self._grid_block is not None:
                    self._grid_block.close()
                self._grid_block = SharedArrays({"first": (np.int64, (cells + cells // 2,))})  # room to grow
                self._stale = True  # the workers map the new block before the push phase
            self._cell_first = self._grid_block.arrays["first"]
        self._cell_first[0] = 0
        np.cumsum(np.bincount(cell, minlength=side * side), out=self._cell_first[1:cells])
        return side

    def _build_list(self, lo: int, hi: int, side: int) -> None:
        """This range's neighbour list from the grid: for each living agent of lo..hi, in agent order,
        the agents of the three rows of three cells around its own (at most SEPARATION_CELL_CAP from
        each row), itself left out, within 2r (r the widest character's radius). An agent's entries are the
        same whichever range it is in. Also notes where the range's agents stand, for the next substeps' move test."""
        r = float(self._separation_radii().max())
        self._pairs_x[lo:hi], self._pairs_z[lo:hi] = self.x[lo:hi], self.z[lo:hi]
        live = lo + np.flatnonzero(self.state[lo:hi] < DYING)
        first_in = self._cell_first  # where each cell's agents start in the grid's order
        cell = self._cell[live]
        rows = np.stack([cell - side, cell, cell + side], axis=1)  # (agents, 3): the middle cell of each row
        start = first_in[rows - 1]
        count = np.minimum(first_in[rows + 2] - start, SEPARATION_CELL_CAP).ravel()
        start = start.ravel()
        total = int(count.sum())
        owner = np.repeat(np.repeat(live, 3), count)
        neighbour = self._cell_order[np.repeat(start - np.cumsum(count) + count, count) + np.arange(total)]
        dx, dz = self.x[owner] - self.x[neighbour], self.z[owner] - self.z[neighbour]
        keep = np.flatnonzero((dx * dx + dz * dz < 4.0 * r * r) & (owner != neighbour))
        self._range_list = (owner[keep], neighbour[keep])

    def neighbour_list(self) -> tuple[np.ndarray, np.ndarray]:
        """(agent, neighbour) entries of the list the last push phase used, for a crowd in one range (tests)."""
        if self.ranges() != 1:
            raise AIError("the neighbour list is split over the workers' ranges")
        return self._range_list


def grid_shape(half: float, size: float, agents: int) -> tuple[float, int]:
    """(cell size, cells a side) of a grid over a world `half` wide each way for `agents` agents (the
    living and the dead: the GPU's twin does not count them): at least `size` wide, so every pair closer
    than `size` is in the same or next cells, but at most about 4 cells an agent (a separation radius far
    below the spacing, a valid setting, must not ask for billions of cells; wider cells only find more
    candidates), with a ring of spare cells round it so that no look at a neighbour cell needs an edge test."""
    size = max(float(size), 2.0 * half / math.sqrt(4.0 * agents + 1.0))
    return size, int(math.ceil(2.0 * half / size)) + 3


def _overlap_push(i, j, dx, dz, dist, r):
    """Per overlapping pair (i, j) at offset (dx, dz) = i - j and distance `dist` < r (the pair's radius,
    one for all or one a pair): the push on i (j gets its opposite), half the overlap along the pair's direction."""
    inv = 1.0 / np.maximum(dist, 1e-12)
    ux, uz = dx * inv, dz * inv
    # Coincident agents: a direction made from the pair's agent numbers (deterministic), pointing from
    # the higher-numbered agent to the lower, so the pair's two entries push its agents apart.
    same = np.flatnonzero(dist < 1e-9)
    if same.size:
        low, high = np.minimum(i[same], j[same]), np.maximum(i[same], j[same])
        angle = 2 * math.pi * np.mod(low * 0.6180339887 + high * 0.7548776662, 1.0)
        sign = np.where(i[same] == low, 1.0, -1.0)
        ux[same], uz[same] = sign * np.cos(angle), sign * np.sin(angle)
    amount = 0.5 * (r - dist)  # each of the two takes half the overlap
    return ux * amount, uz * amount


def _sort_cells(cell: np.ndarray, cells: int) -> np.ndarray:
    """Stable argsort of cell numbers. numpy sorts 16-bit keys by radix, about 15x faster than the
    comparison sort wider keys get, so wider numbers are sorted as two 16-bit digits, low digit first."""
    if cells <= 1 << 16:
        return np.argsort(cell.astype(np.uint16), kind="stable")
    if cells > 1 << 32:
        return np.argsort(cell, kind="stable")
    low = np.argsort((cell & 0xFFFF).astype(np.uint16), kind="stable")
    return low[np.argsort((cell[low] >> 16).astype(np.uint16), kind="stable")]
