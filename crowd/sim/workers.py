"""Several cores (setting workers; crowd.sim.agent_pool): a crowd of 2 x MIN_RANGE agents or more is cut
into ranges of consecutive agents, one per process, its arrays in shared memory; each substep is a few
phases with a barrier between them (``_substep``). Random draws are keyed by agent and substep and
each range builds its own neighbour list from one shared grid, so any number of workers gives the
same crowd, bit for bit. Arrays are changed in place, never rebound, so the workers see every change
the main process makes between steps (``hit``, the tests' placements).
"""

from __future__ import annotations

import numpy as np

from .agent_pool import PARAMS, AgentPool, PoolError, SharedArrays, available_cores
from .config import AIError
from .locomotion import _KIND_FIELDS

MIN_RANGE = 1_024  # agents a process steps at least: a smaller share saves less than waking a worker costs
# Phases of a substep (run on every range of agents, a barrier between two) and their numbers' places.
THINK, PUSH, APPLY, FINISH, WRITE_LAYERS, HEADINGS = 1, 2, 3, 4, 5, 6
P_H, P_TIME, P_SUBSTEPS, P_STEPS, P_PLAYER, P_RANGES, P_N, P_BLOCK, P_GAIN, P_HAVE_PAIRS, P_REBUILD, P_SIDE = (
    1, 2, 3, 4, 5, 7, 8, 9, 11, 12, 13, 14)
P_FOCUS_COUNT, P_FOCUS = 15, 16
MAX_FOCUS = (PARAMS - P_FOCUS) // 2


class WorkersMixin:
    """CrowdAI's part that cuts a substep's phases over ranges of agents and runs them on the worker pool."""

    def _phase(self, code: int, ranges: int) -> np.ndarray:
        """Phase `code` on every range: range 0 here, ranges 1.. in the workers. Returns each range's
        answer, (ranges, 3)."""
        p = self._params
        p[0], p[P_RANGES], p[P_N] = code, ranges, self.n
        if ranges == 1:
            return np.array([self.run_phase(code, p, -1)], np.float64)
        mine = []
        theirs = self._on_pool(self._pool.run, code, ranges - 1, lambda: mine.append(self.run_phase(code, p, -1)))
        return np.concatenate([np.array([mine[0]], np.float64), theirs[:, :3]])

    def _workers(self) -> int:
        """Processes that may step the crowd, this one included (the ``workers`` setting; 0: one per core)."""
        return self.config.workers or min(available_cores(), 64)

    def _ready_ranges(self) -> int:
        """How many ranges this substep's crowd is cut into (at least MIN_RANGE agents each), with the
        worker pool started, stopped or told of new arrays and settings as that needs."""
        ranges = self.ranges()
        if self._pool is not None and self._pool.closed:  # it failed or was interrupted: a new one is started
            self._stop_pool(copy=False)
        if ranges > 1 and self._pool is None:
            self._start_pool(self._workers() - 1)
        if ranges > 1:
            self._sync_workers()
        return ranges

    def _sync_workers(self) -> None:
        """Tell the workers of new arrays or settings, if there are any since they last heard."""
        if self._stale:
            grid = self._grid_block
            message = dict(block=(self._block.name, self._block.layout), grid=(grid.name, grid.layout) if grid else None,
                           config=self.config, motions=self.motions, shares=self.shares, cast=self.cast, seed=self.seed,
                           origin=self.origin, half_extent=self.half_extent, n=self.n, obstacles=self.obstacles)
            self._on_pool(self._pool.sync, [message] * self._pool.workers)
            self._stale = False

    def _on_pool(self, call, *args):
        """`call(*args)` on the pool; a worker that failed or exited is the AI's one line, and the pool is
        dropped (the arrays stay where they are; the next substep starts a new pool)."""
        try:
            return call(*args)
        except PoolError as error:
            self._stop_pool(copy=False)
            raise AIError(str(error)) from None

    def _start_pool(self, workers: int) -> None:
        """Start the workers and move the agents' arrays (and the neighbour list) into shared memory."""
        try:
            self._pool = AgentPool(workers, type(self).worker_side)
        except (OSError, PoolError) as error:
            raise AIError(f"AI workers could not start: {str(error).splitlines()[0]}") from None
        self._params = self._pool.params  # the phases' numbers, now read by the workers too
        self._rehome()

    def _stop_pool(self, copy: bool = True) -> None:
        """Stop the workers; the arrays go back to this process's memory (`copy`: with their state)."""
        pool, self._pool = self._pool, None
        if pool is not None:
            self._params = self._params.copy()
            pool.close()
        if copy:
            self._rehome()

    def _rehome(self) -> None:
        """The same arrays, values and neighbour list in the memory the pool's state asks for."""
        kept = {name: getattr(self, name) for name in self._layout(self.n)}
        was = self._allocate(self.n)  # (the neighbour lists are built anew: each range's is its process's own)
        for name, array in kept.items():
            getattr(self, name)[...] = array
        del kept
        if was is not None:
            was.close()

    def take_workers(self, other: WorkersMixin) -> None:
        """Step with `other`'s worker processes from now on (a new round's new crowd: starting 15 processes
        again froze the first frame of every round for 0.4 s on the dev container, 1 s on the H200 host).
        `other` is left without them (and is to be closed); nothing happens if it has none, if one of them
        has exited, or if they are another size."""
        pool = other._pool
        if pool is None or not pool.healthy or self._pool is not None or other.config.workers != self.config.workers:
            return  # (a pool that lost a worker is left to `other`, whose close() stops it; this crowd starts its own)
        other._pool, other._params = None, other._params.copy()  # `other` keeps its arrays: its close() frees them
        params = self._params
        self._pool, self._params = pool, pool.params
        try:
            self._rehome()  # this crowd's arrays into shared memory; the next substep tells the workers (_stale)
        except BaseException:
            self._pool, self._params = None, params
            pool.close()
            raise

    def close(self) -> None:
        """Stop the worker processes and free the shared memory (also done when the AI is collected)."""
        self._stop_pool(copy=True)
        if self._grid_block is not None:
            self._grid_block.close()
            self._grid_block = None

    @classmethod
    def worker_side(cls) -> WorkersMixin:
        """The AI in a worker process: arrays mapped from the main process's block by ``sync_worker``."""
        ai = cls.__new__(cls)
        ai._block = ai._grid_block = ai._pool = ai._range_list = None
        ai._respawns, ai.player_hits_taken, ai.focus = 0, 0, ()  # (a worker spawns only at edges)
        ai.obstacles = None
        return ai

    def sync_worker(self, message: dict | None) -> None:
        """(A worker) map the arrays and take the settings the main process sent; None: unmap all."""
        for name in list(self.__dict__):
            if isinstance(self.__dict__[name], np.ndarray) and name not in ("origin", "player"):
                del self.__dict__[name]
        for block in (self._block, self._grid_block):
            if block is not None:
                block.close()
        self._block = self._grid_block = None
        if message is None:
            return
        self.config, self.motions, self.shares, self.seed = message["config"], message["motions"], message["shares"], message["seed"]
        if getattr(self, "obstacles", None) is None or message["obstacles"] is None or self.obstacles.boxes != message["obstacles"].boxes:
            self.obstacles = message["obstacles"]  # (its distance field is built here, on first use; the flow field is shared)
        self.origin, self.half_extent, self.n, self.cast = message["origin"], message["half_extent"], message["n"], message["cast"]
        self._kind_fields = _KIND_FIELDS if len(self.motions) > 1 else ()
        self._motion_tables()
        self._layer_template = {}
        self._block = SharedArrays(*reversed(message["block"]))
        for name, array in self._block.arrays.items():
            setattr(self, name, array)
        if message["grid"] is not None:
            self._grid_block = SharedArrays(*reversed(message["grid"]))
            self._cell_first = self._grid_block.arrays["first"]

    def run_phase(self, code: int, p: np.ndarray, index: int) -> tuple:
        """Phase `code` on this process's share of the agents (range index + 1 of p's count; the main
        process is index -1), with the substep's numbers `p`. Returns up to three numbers."""
        ranges, n, r = int(p[P_RANGES]), int(p[P_N]), index + 1
        lo, hi = r * n // ranges, (r + 1) * n // ranges
        if index >= 0:  # a worker: the substep's numbers, as the main process holds them
            self.time, self.substeps, self.steps = float(p[P_TIME]), int(p[P_SUBSTEPS]), int(p[P_STEPS])
            self.player = p[P_PLAYER:P_PLAYER + 2].copy()
            self.focus = tuple(p[P_FOCUS + 2 * f:P_FOCUS + 2 * f + 2].copy() for f in range(int(p[P_FOCUS_COUNT])))
        h = float(p[P_H])
        if code == THINK:
            block = None
            if p[P_BLOCK] >= 0:  # this process's share of the budget's block: a slice of it, not of its range
                b0, b1 = int(p[P_BLOCK]), int(p[P_BLOCK + 1])
                block = (b0, b1, slice(b0 + r * (b1 - b0) // ranges, b0 + (r + 1) * (b1 - b0) // ranges))
            return self._think_range(lo, hi, h, block, bool(p[P_HAVE_PAIRS]))
        if code == PUSH:
            if p[P_REBUILD]:
                self._build_list(lo, hi, int(p[P_SIDE]))
            self._range["push"] = self._push_range(lo, hi, float(p[P_GAIN]))
        elif code == APPLY:
            self._apply_range(lo, hi, self._range.pop("push"))
        elif code == FINISH:
            self._finish_range(lo, hi, h)
        elif code == WRITE_LAYERS:
            self._write_layer_range(self._layer_out, lo, hi)
        elif code == HEADINGS:
            np.arctan2(self.hx[lo:hi], self.hz[lo:hi], out=self._yaw_out[lo:hi], casting="same_kind")
        else:
            raise AIError(f"unknown AI phase {code}")
        return (0.0, 0.0, 0.0)

    def ranges(self) -> int:
        """Processes that step the crowd now, this one included (1 below 2 x MIN_RANGE agents)."""
        return max(1, min(self._workers(), self.n // MIN_RANGE))
