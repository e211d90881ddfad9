"""The crowd among obstacles: agents kept clear of them, and the flow field chasers follow around
buildings."""

from __future__ import annotations

import math

import numpy as np

# Obstacles (a town: crowd.asset.town.Obstacles). An agent's centre is kept CLEARANCE metres from every
# obstacle, by its signed distance field; chasers find their way around buildings by a flow field of
# FLOW_CELLS x FLOW_CELLS cells of FLOW_CELL metres around the player, made anew when the player
# crosses a cell.
CLEARANCE = 0.35
FLOW_CELL = 1.0
FLOW_CELLS = 96
FLOW_BLOCKED = CLEARANCE + 0.05  # a flow cell whose centre is nearer an obstacle than this is a wall (a 2 m alley stays open)
FLOW_DIRECT = 3.0  # metres from the player within which a chaser goes straight at it
_FLOW_ARRAYS = ("_flow_steps", "_flow_usable", "_flow_corner")
# A field takes 4.5 to 5 ms on the dev container (about 70 units of flow_field_work): made in one substep
# it made the AI's slowest substeps. The main process does FLOW_WORK units a substep, before the think,
# and publishes the field into the agents' shared arrays when it is done (about 6 substeps, 0.1 s, after
# the player crossed into the cell), so every process steps with the same field: the same crowd for any
# worker count, and any machine.
FLOW_WORK = 12


def _relaxations(open_: np.ndarray, target: tuple[int, int]):
    """Shortest 8-neighbour path lengths (in cells; diagonals sqrt 2) from every open cell of a grid to
    `target`, inf where walled off, as a generator: None after each relaxation pass, then the lengths. Every
    cell relaxed from its 8 neighbours at once, until nothing shortens (a pass per cell of the longest
    path: 54 to 67 passes, 4 to 5 ms for the town's 96 x 96 window on the dev container). Written here
    rather than taken from scipy (csgraph's Dijkstra): the AI is numpy only, this is the one graph
    search it needs, and passes can be spread over substeps (_update_flow). A version relaxing whole
    lines at once (running minimums along rows, columns and diagonals) needed 7 passes but took 4.3 ms:
    numpy's running minimum costs more per cell than the passes it saves."""
    n, m = open_.shape
    dist = np.full((n, m), np.inf)
    dist[target] = 0.0
    steps = [(di, dj, math.hypot(di, dj)) for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj]
    for _ in range(4 * max(n, m)):
        before = dist.copy()
        for di, dj, w in steps:
            a = dist[max(di, 0):n + min(di, 0), max(dj, 0):m + min(dj, 0)]
            b = before[max(-di, 0):n + min(-di, 0), max(-dj, 0):m + min(-dj, 0)]
            np.minimum(a, b + w, out=a)
        dist[~open_] = np.inf
        dist[target] = 0.0
        if np.array_equal(dist, before):
            break
        yield None
    yield dist


def flow_field(obstacles, cell: tuple[int, int]) -> tuple:
    """The flow field toward the player's `cell` (see flow_field_work), made at once."""
    work = flow_field_work(obstacles, cell)
    while True:
        field = next(work)
        if field is not None:
            return field


def flow_field_work(obstacles, cell: tuple[int, int]):
    """The flow field toward the player's `cell`, as a generator of units of work of 0.05 to 0.3 ms (None),
    the last of which gives the field: (the window's first cell's corner (x, z), each cell's way down the
    path distances: di and dj (int8), and whether there is one), over FLOW_CELLS x FLOW_CELLS cells of
    FLOW_CELL metres centred on it (a cell whose centre is within FLOW_BLOCKED of an obstacle is a wall).
    The units are fixed by the field alone, not by time, so a field spread over substeps comes in at the
    same substep on any machine."""
    cell = np.asarray(cell, np.int64)
    corner = (cell - FLOW_CELLS // 2) * FLOW_CELL
    centres = corner[:, None] + (np.arange(FLOW_CELLS) + 0.5) * FLOW_CELL
    cx, cz = np.meshgrid(centres[0], centres[1], indexing="ij")
    open_ = obstacles.distance(cx, cz) >= FLOW_BLOCKED
    yield None
    passes = _relaxations(open_, (FLOW_CELLS // 2, FLOW_CELLS // 2))
    while (dist := next(passes)) is None:
        yield None
    dist *= FLOW_CELL
    downhill = _downhill(dist)
    while (steps := next(downhill)) is None:
        yield None
    step_i, step_j, usable = steps
    yield corner.astype(np.float64), step_i.astype(np.int8), step_j.astype(np.int8), usable


def _downhill(dist: np.ndarray):
    """Each cell's way down the distances: the neighbour (di, dj) nearest the target by path, and whether
    it is nearer than the cell itself (walls are inf). A cell the field calls a wall (an agent pressed
    against one stands in one) looks two cells out. Per cell, once per field: the chasers look it up.
    A generator: None after each row of 5 neighbours, then (di, dj, whether)."""
    n = dist.shape[0]
    padded = np.full((n + 4, n + 4), np.inf)
    padded[2:-2, 2:-2] = dist
    reach = np.where(np.isfinite(dist), 1, 2)
    best = np.full(dist.shape, np.inf)
    step_i, step_j = np.zeros(dist.shape, np.int64), np.zeros(dist.shape, np.int64)
    for di in range(-2, 3):
        for dj in range(-2, 3):
            if di or dj:
                d = np.where(max(abs(di), abs(dj)) <= reach, padded[2 + di:n + 2 + di, 2 + dj:n + 2 + dj], np.inf)
                better = d < best
                best = np.where(better, d, best)
                step_i, step_j = np.where(better, di, step_i), np.where(better, dj, step_j)
        yield None
    yield step_i, step_j, np.isfinite(best) & (best < dist)


class ObstaclesMixin:
    """CrowdAI's part that keeps agents out of the obstacles and steers chasers by the flow field."""

    def _free_share(self) -> float:
        return 1.0 if self.obstacles is None else self.obstacles.free_share

    def keep_out(self, x, z, iterations: int = 4) -> tuple[np.ndarray, np.ndarray]:
        """Points (x, z) moved out along the obstacle field's gradient until CLEARANCE from every
        obstacle (each move aims 5 mm past it: the field is bilinear, not linear), and into the world;
        a point in a corner between two obstacles steps out of both in a few moves."""
        x, z = np.array(x, np.float64), np.array(z, np.float64)
        o, e = self.obstacles, self.half_extent
        ox, oz = self.origin
        for _ in range(iterations):
            d = o.distance(x, z)
            near = np.flatnonzero(d < CLEARANCE)
            if not near.size:
                break
            gx, gz = o.gradient(x[near], z[near])
            move = CLEARANCE + 0.005 - d[near]
            x[near] = np.minimum(np.maximum(x[near] + gx * move, ox - e), ox + e)
            z[near] = np.minimum(np.maximum(z[near] + gz * move, oz - e), oz + e)
        return x, z

    def _clear_obstacles(self, lo: int, hi: int) -> None:
        """Agents lo..hi out of the obstacles (CLEARANCE from each), and their velocity into them stopped:
        they slide along a wall instead of pressing into it. A nearest-cell look first, so only the
        agents near an obstacle pay for the bilinear field and its gradient."""
        o = self.obstacles
        x, z = self.x[lo:hi], self.z[lo:hi]
        near = np.flatnonzero(o.cell_distance(x, z) < CLEARANCE + o.cell)
        if not near.size:
            return
        cx, cz = self.keep_out(x[near], z[near])
        moved = (cx != x[near]) | (cz != z[near])
        if not moved.any():
            return
        agents = near[moved]
        x[agents], z[agents] = cx[moved], cz[moved]
        gx, gz = o.gradient(x[agents], z[agents])
        vx, vz = self.vx[lo:hi], self.vz[lo:hi]
        into = np.minimum(vx[agents] * gx + vz[agents] * gz, 0.0)
        vx[agents] -= into * gx
        vz[agents] -= into * gz

    def _update_flow(self) -> None:
        """(The main process, before a substep's think.) Do FLOW_WORK units of the field toward the
        player's cell, started when the player has left the published field's cell and none is being
        made, and publish it into the shared arrays when it is done."""
        if self.obstacles is None:
            return
        cell = tuple(int(c) for c in np.floor(np.asarray(self.player, np.float64) / FLOW_CELL))
        if self._flow_job is None:
            if cell == self._flow_cell:
                return
            self._flow_job = (cell, flow_field_work(self.obstacles, cell))
        for _ in range(FLOW_WORK):
            field = next(self._flow_job[1])
            if field is not None:
                corner, step_i, step_j, usable = field
                self._flow_steps[0], self._flow_steps[1], self._flow_usable[...] = step_i, step_j, usable
                self._flow_corner[:] = corner[0], corner[1], 1.0
                self._flow_cell, self._flow_job = self._flow_job[0], None
                return

    def _flow_field(self) -> tuple | None:
        """The published flow field: (the window's first cell's corner (x, z), each cell's way down the
        path distances to the player: the neighbour (di, dj), and whether there is one); None without
        obstacles or before the first field is in."""
        if self.obstacles is None or not self._flow_corner[2]:
            return None
        return self._flow_corner[:2], self._flow_steps[0], self._flow_steps[1], self._flow_usable

    def _flow_directions(self, x: np.ndarray, z: np.ndarray, to_x: np.ndarray, to_z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Directions (unit, x and z) chasers at (x, z) take toward the player: toward the centre of their
        cell's way down the flow field where they are in its window and not within FLOW_DIRECT of the
        player, else straight (`to_x`, `to_z`: their offsets to the player)."""
        straight = np.hypot(to_x, to_z)
        ux, uz = to_x / np.maximum(straight, 1e-12), to_z / np.maximum(straight, 1e-12)
        flow = self._flow_field()
        if flow is None:
            return ux, uz
        corner, step_i, step_j, usable = flow
        i = np.floor((x - corner[0]) / FLOW_CELL).astype(np.int64)
        j = np.floor((z - corner[1]) / FLOW_CELL).astype(np.int64)
        inside = (i >= 1) & (i < FLOW_CELLS - 1) & (j >= 1) & (j < FLOW_CELLS - 1) & (straight > FLOW_DIRECT)
        k = np.flatnonzero(inside)
        if not k.size:
            return ux, uz
        i, j = i[k], j[k]
        # Toward that neighbour's centre from where the agent stands (not from its own cell's centre).
        tx = corner[0] + (i + step_i[i, j] + 0.5) * FLOW_CELL - x[k]
        tz = corner[1] + (j + step_j[i, j] + 0.5) * FLOW_CELL - z[k]
        norm = np.maximum(np.hypot(tx, tz), 1e-12)
        go = usable[i, j]
        ux[k] = np.where(go, tx / norm, ux[k])
        uz[k] = np.where(go, tz / norm, uz[k])
        return ux, uz
