"""The process's allocator, set for a frame loop that makes large numpy temporaries every frame.

numpy takes each array's memory from malloc. glibc serves blocks above its mmap threshold with a
fresh mmap and gives them back on free, and it trims the heap's free top back to the kernel; both
thresholds adapt, but a frame whose temporaries come and go in waves (the AI's whole-array steps,
the records, the weapons) keeps returning memory and faulting it in again, zeroed by the kernel, a
page at a time. At 100,000 agents that was 121,000 page faults a frame (about 470 MB) on the dev
container, and on the H200 machine's host (a virtual machine, where a fault costs more) the frame
period went from 94.6 to 65.2 ms when glibc was told to keep its memory (docs/BENCHMARKS.md, "The
allocator"). So the frame loop fixes both thresholds once: no block a crowd's frame allocates is
mapped for itself, and freed memory stays with the process for the next frame. The price is that
the process keeps its largest frame's memory until it exits, which a game does anyway.

Only glibc has these knobs; elsewhere (macOS, Windows, musl) this does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import platform

M_TRIM_THRESHOLD = -1  # glibc's malloc.h
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 * 1024 * 1024  # glibc's largest (DEFAULT_MMAP_THRESHOLD_MAX on 64-bit): one million agents' float64 column is 8 MB
TRIM_THRESHOLD = 1 << 30


@functools.cache
def keep_freed_memory() -> bool:
    """Fix glibc's mmap and trim thresholds for this process (once); True where they were set."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return bool(libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    except (OSError, AttributeError):
        return False
