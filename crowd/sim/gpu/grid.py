"""A uniform grid of agents on the GPU (shaders/sim/grid.comp.glsl), built by a counting sort: each
agent's cell, each cell's count, an exclusive prefix sum over the cells (in work groups of 256, then
their totals in one group, then added back), the agents scattered into their cells' slots, and each
cell's agents sorted by number. The last pass is what makes the grid deterministic: atomics decide only
which slot of its cell an agent lands in, and the sort makes that order the numpy grid's (a stable sort
by cell), so a pass that reads a cell reads the same agents in the same order on every run.

The AI's separation reads it (crowd.sim.gpu.ai) and so does ``crowd-bench circles``. The numpy twin:
crowd.sim.separation's ``_build_grid``."""

from __future__ import annotations

import contextlib

import moderngl
import numpy as np

from ...gl import GLObjects, GLStage, load_shader, set_uniforms

GROUP = 256
SHADER_STORAGE = 0x2000  # GL_SHADER_STORAGE_BARRIER_BIT
CELL, COUNT, FIRST, BLOCKS, SORTED, PAYLOAD = 10, 11, 12, 13, 14, 16  # the grid's storage bindings



class NeighbourGrid(GLStage):
    """The grid's buffers (grown, never shrunk, as the crowd or the world grows) and its passes."""

    def __init__(self, ctx: moderngl.Context, live_only: bool):
        self.ctx = ctx
        self._objects = GLObjects()
        defines = {"LIVE_ONLY": 1, "PAYLOAD": 1} if live_only else {"PAYLOAD": 1}
        self._programs = {name: self._objects.add(ctx.compute_shader(load_shader("sim/grid.comp.glsl", {name: 1, **defines})))
                          for name in ("COUNT", "SCAN_LOCAL", "SCAN_BLOCKS", "SCAN_ADD", "SCATTER", "ORDER")}
        self._buffers: dict[int, moderngl.Buffer] = {}
        self.cells = self.side = 0
        self.builds = 0

    def _buffer(self, binding: int, size: int, zero: bool = False) -> moderngl.Buffer:
        """The buffer of `binding`, at least `size` bytes: a new one (zeroed where asked) if it was smaller,
        or over four times bigger (a crowd that shrank gives its memory back)."""
        old = self._buffers.get(binding)
        if old is not None and size <= old.size <= 4 * size + 64:
            return old
        size = max(size + size // 2, 16)  # room to grow
        new = self._objects.add(self.ctx.buffer(bytes(size) if zero else None, reserve=0 if zero else size))
        if old is not None:
            self._objects.remove(old)
            old.release()
        self._buffers[binding] = new
        return new

    def build(self, points: moderngl.Buffer, n: int, corner: tuple[float, float], size: float, side: int, timer=None) -> None:
        """Sort agents 0..n (their x, z the first two floats of each vec4 of `points`, bound at 0; with
        live_only, their state the first int of the codes at 5) into `side` x `side` cells of `size`,
        cell (1, 1)'s corner at `corner`, each slot's agent's vec4 of `points` copied beside it (the
        payload). Leaves the grid bound for the pass that reads it; `filled` (agents in the grid) is
        first[cells]."""
        cells = side * side
        blocks = (cells + GROUP - 1) // GROUP
        self._buffer(CELL, 4 * n)
        self._buffer(COUNT, 4 * cells, zero=True)  # (every build leaves it zero again)
        self._buffer(FIRST, 4 * (cells + 1))
        self._buffer(BLOCKS, 4 * blocks)
        self._buffer(SORTED, 4 * n)
        self._buffer(PAYLOAD, 16 * n)
        self.bind()
        points.bind_to_storage_buffer(0)
        self.cells, self.side = cells, side
        for program in self._programs.values():
            set_uniforms(program, u_n=n, u_cells=cells, u_side=side, u_corner=corner, u_inv_size=1.0 / size, u_blocks=blocks)
        agents = (n + GROUP - 1) // GROUP
        for name, groups in (("COUNT", agents), ("SCAN_LOCAL", blocks), ("SCAN_BLOCKS", 1), ("SCAN_ADD", blocks), ("SCATTER", agents),
                             ("ORDER", blocks)):
            with timer.gpu(f"grid_{name.lower()}") if timer is not None else contextlib.nullcontext():
                self._programs[name].run(groups)
                self.ctx.memory_barrier(SHADER_STORAGE)
        self.builds += 1

    def clear(self) -> None:
        """No grid (no crowd): every buffer given back."""
        for buffer in self._buffers.values():
            self._objects.remove(buffer)
            buffer.release()
        self._buffers = {}
        self.cells = self.side = 0

    def bind(self) -> None:
        for binding, buffer in self._buffers.items():
            buffer.bind_to_storage_buffer(binding)

    def read(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(each agent's cell, each cell's first slot (cells + 1), the agents in cell order): tests."""
        cell = np.frombuffer(self._buffers[CELL].read(4 * n), np.uint32)
        first = np.frombuffer(self._buffers[FIRST].read(4 * (self.cells + 1)), np.uint32)
        return cell, first, np.frombuffer(self._buffers[SORTED].read(4 * n), np.uint32)

    def gpu_bytes(self) -> int:
        return self._objects.gpu_bytes()

    def release(self) -> None:
        self._objects.release()
        self._buffers = {}
