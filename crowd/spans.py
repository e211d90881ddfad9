"""Per-agent numpy work split across the host's cores, in threads.

The render side's frame is a dozen whole-crowd numpy passes in the main process (the instance
records, the layers' contract check, the foot lock's motion, ...): at 1,000,000 agents about 150 ms
of one core on the H200 machine's host while its other 15 cores wait (docs/BENCHMARKS.md, "The CPU
side of the frame"). numpy lets go of the GIL inside its loops (ufuncs, casts, copies, reductions),
so the same passes over slices of the agents run side by side in plain threads, with no copies and
no processes. A span is at least `MIN_SPAN` agents: below that a thread's hand-off (tens of
microseconds) costs more than the slice's work, so a small crowd runs in the calling thread exactly
as before.

Each caller writes disjoint slices of its own output arrays, so no span waits for another. A span's
work must not call ``over_spans`` itself: the pool's threads would wait on each other.
"""

from __future__ import annotations

import atexit
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, TypeVar

import numpy as np

MIN_SPAN = 50_000  # agents
MAX_THREADS = 8  # the passes are memory-bound: more threads than this stopped paying on the H200 host

T = TypeVar("T")
_pool: ThreadPoolExecutor | None = None
_pool_made = threading.Lock()


def thread_count() -> int:
    """Threads the spans may use: the cores this process may run on, at most MAX_THREADS."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # (not on macOS or Windows)
        cores = os.cpu_count() or 1
    return max(1, min(MAX_THREADS, cores))


def spans(n: int, min_span: int | None = None) -> list[tuple[int, int]]:
    """[lo, hi) slices that cover 0..n, at most one a thread, none shorter than `min_span` (default
    MIN_SPAN; one slice, possibly empty, for a small n)."""
    count = max(1, min(thread_count(), n // max(1, MIN_SPAN if min_span is None else min_span)))
    edges = [n * k // count for k in range(count + 1)]
    return list(zip(edges[:-1], edges[1:]))


def over_spans(work: Callable[[int, int], T], n: int, min_span: int | None = None) -> list[T]:
    """`work(lo, hi)` for each of ``spans(n)``, in threads where there is more than one; the results in
    order. An exception in any span is raised here once every span has ended (none is left running
    over arrays the caller is about to drop)."""
    parts = spans(n, min_span)
    if len(parts) == 1:
        return [work(*parts[0])]
    global _pool
    with _pool_made:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=thread_count(), thread_name_prefix="crowd-span")
            atexit.register(_pool.shutdown, wait=False)
    futures = [_pool.submit(work, lo, hi) for lo, hi in parts]
    errors = [f.exception() for f in futures]  # (waits for each)
    for error in errors:
        if error is not None:
            raise error
    return [f.result() for f in futures]


def min_max(a) -> tuple[float, float]:
    """The smallest and largest value of an array (NaN where it holds one: NaN carries through both),
    reduced over spans of its first axis side by side. (0.0, 0.0) for an empty array."""
    a = np.asarray(a)
    if not a.size:
        return 0.0, 0.0
    parts = over_spans(lambda lo, hi: (a[lo:hi].min(), a[lo:hi].max()), len(a))
    return float(np.min([p[0] for p in parts])), float(np.max([p[1] for p in parts]))
