"""Per-pass timings: GPU passes through timer queries, CPU passes through perf_counter.

GPU results are read one ring slot later than they were issued (a ring of 3 query sets), so reading
a timing never waits for the GPU in a windowed frame loop. Medians are what the stats report.
"""

from __future__ import annotations

import time

import moderngl
import numpy as np

from .gl import GLStage, flush_function

RING = 3
KEEP = 100_000  # samples kept per pass: a window left running for hours does not grow without bound


class SampleRing:
    """The last KEEP samples of a measure, in one float64 array (8 bytes a sample, where a deque of
    floats took about 40): appending never allocates, so a long run's memory stays flat once full.
    ``np.asarray(ring)`` gives them oldest first; ``total`` counts the samples appended since the last
    ``clear()``, kept or not."""

    def __init__(self, capacity: int = KEEP):
        self._values = np.zeros(capacity)
        self._next = 0
        self.total = 0

    def append(self, value: float) -> None:
        self._values[self._next] = value
        self._next = (self._next + 1) % len(self._values)
        self.total += 1

    def clear(self) -> None:
        self._next = self.total = 0

    def __len__(self) -> int:
        return min(self.total, len(self._values))

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        kept = len(self)
        out = np.roll(self._values, -self._next)[len(self._values) - kept:] if kept == len(self._values) else self._values[:kept].copy()
        return out if dtype is None else out.astype(dtype)

    def recent(self, count: int) -> np.ndarray:
        """The last `count` samples, newest first (only those are read: the panel asks every frame)."""
        count = min(count, len(self))
        return self._values[(self._next - 1 - np.arange(count)) % len(self._values)]


class PassTimer(GLStage):
    def __init__(self, ctx: moderngl.Context | None):
        self.ctx = ctx
        self.frame = 0
        self._queries: dict[str, list] = {}
        self._pending: list[tuple[int, str, object]] = []
        self._flush = None  # glFlush, looked up on the first GPU pass
        self.samples: dict[str, SampleRing] = {}
        self.clock: dict[str, str] = {}
        self.order: list[str] = []
        self._spans: dict = {}

    def _note(self, name: str, clock: str) -> None:
        if name not in self.clock:
            self.clock[name] = clock
            self.order.append(name)

    def cpu(self, name: str) -> "_CpuSpan":
        """``with timer.cpu(name):`` times its body on the CPU clock. One span object per name, kept:
        a frame opens about 20 spans, and a generator-based context manager cost 5 µs each."""
        span = self._spans.get(name)
        if span is None:
            self._note(name, "cpu")
            span = self._spans[name] = _CpuSpan(self._samples(name))
        return span

    def gpu(self, name: str) -> "_GpuSpan":
        """``with timer.gpu(name):`` times its body on the GPU through a timer query of this frame's ring slot."""
        span = self._spans.get(name)
        if span is None:
            self._note(name, "gpu")
            span = self._spans[name] = _GpuSpan(self, name)
        return span

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

    def _samples(self, name: str) -> SampleRing:
        if name not in self.samples:
            self.samples[name] = SampleRing()
        return self.samples[name]

    def recent(self, name: str, count: int) -> np.ndarray:
        """The last `count` samples of a pass, newest first (the panel's live numbers)."""
        ring = self.samples.get(name)
        return ring.recent(count) if ring is not None else np.zeros(0)

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


class _CpuSpan:
    __slots__ = ("ring", "start")

    def __init__(self, ring: SampleRing):
        self.ring = ring

    def __enter__(self):
        self.start = time.perf_counter()

    def __exit__(self, *exc):
        self.ring.append((time.perf_counter() - self.start) * 1e3)
        return False


class _GpuSpan:
    __slots__ = ("timer", "name", "query")

    def __init__(self, timer: PassTimer, name: str):
        self.timer, self.name, self.query = timer, name, None

    def __enter__(self):
        timer = self.timer
        if timer.ctx is None:
            return
        ring = timer._queries.setdefault(self.name, [None] * RING)
        slot = timer.frame % RING
        if ring[slot] is None:
            ring[slot] = timer.ctx.query(time=True)
        self.query = ring[slot]
        self.query.__enter__()

    def __exit__(self, *exc):
        timer, query = self.timer, self.query
        if query is None:
            return False
        self.query = None
        query.__exit__(None, None, None)
        # Flush (never wait): a timer query counts from when the GPU reaches its begin to when it reaches
        # its end, so an end left in the driver's command buffer until something else flushes it counts
        # the CPU work in between. The GPU cull's dispatch took 0.07 ms for 1,000,000 agents timed alone
        # and read 194 ms in the frame, where the weapons' CPU placement came next.
        if timer._flush is None:
            timer._flush = flush_function()
        timer._flush()
        timer._pending.append((timer.frame, self.name, query))
        return False
