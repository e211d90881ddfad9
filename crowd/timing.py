"""Per-pass timings: GPU passes through timer queries, CPU passes through perf_counter.

GPU results are read one ring slot later than they were issued (a ring of 3 query sets), so reading
a timing never waits for the GPU in a windowed frame loop. Medians are what the stats report.
"""

from __future__ import annotations

import itertools
import time
from collections import deque
from contextlib import contextmanager

import moderngl
import numpy as np

from .gl import GLStage, flush_function

RING = 3
KEEP = 100_000  # samples kept per pass: a window left running for hours does not grow without bound


class PassTimer(GLStage):
    def __init__(self, ctx: moderngl.Context | None):
        self.ctx = ctx
        self.frame = 0
        self._queries: dict[str, list] = {}
        self._pending: list[tuple[int, str, object]] = []
        self._flush = None  # glFlush, looked up on the first GPU pass
        self.samples: dict[str, deque] = {}
        self.clock: dict[str, str] = {}
        self.order: list[str] = []

    def _note(self, name: str, clock: str) -> None:
        if name not in self.clock:
            self.clock[name] = clock
            self.order.append(name)

    @contextmanager
    def cpu(self, name: str):
        self._note(name, "cpu")
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._samples(name).append((time.perf_counter() - t0) * 1e3)

    @contextmanager
    def gpu(self, name: str):
        self._note(name, "gpu")
        if self.ctx is None:
            yield
            return
        ring = self._queries.setdefault(name, [None] * RING)
        slot = self.frame % RING
        if ring[slot] is None:
            ring[slot] = self.ctx.query(time=True)
        query = ring[slot]
        with query:
            yield
        # Flush (never wait): a timer query counts from when the GPU reaches its begin to when it reaches
        # its end, so an end left in the driver's command buffer until something else flushes it counts
        # the CPU work in between. The GPU cull's dispatch took 0.07 ms for 1,000,000 agents timed alone
        # and read 194 ms in the frame, where the weapons' CPU placement came next.
        if self._flush is None:
            self._flush = flush_function()
        self._flush()
        self._pending.append((self.frame, name, query))

    def end_frame(self, drain: bool = False) -> None:
        """Collect queries issued RING - 1 frames ago (all of them when drain is set)."""
        keep = []
        for frame, name, query in self._pending:
            if drain or frame <= self.frame - (RING - 1):
                self._samples(name).append(query.elapsed / 1e6)
            else:
                keep.append((frame, name, query))
        self._pending = keep
        self.frame += 1

    def _samples(self, name: str) -> deque:
        if name not in self.samples:
            self.samples[name] = deque(maxlen=KEEP)
        return self.samples[name]

    def recent(self, name: str, count: int) -> list[float]:
        """The last `count` samples of a pass (the panel's live numbers)."""
        return list(itertools.islice(reversed(self.samples.get(name, ())), count))

    def medians(self) -> dict[str, float]:
        return {name: round(float(np.median(self.samples[name])), 4) for name in self.order if self.samples.get(name)}

    def release(self) -> None:
        self.end_frame(drain=True)
        for ring in self._queries.values():
            for q in ring:
                release = getattr(q, "release", None)  # moderngl 5.x queries have none: the context frees them
                if release is not None:
                    release()
        self._queries.clear()
