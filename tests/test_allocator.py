"""crowd.allocator: a frame loop's large temporaries reuse memory instead of being faulted in again.
Each case runs in a fresh interpreter: the setting is process-wide, and other tests build pipelines
(which make it)."""

import platform
import subprocess
import sys

import pytest

FRAMES = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from crowd.allocator import keep_freed_memory
    assert keep_freed_memory()
a = np.random.default_rng(0).random(1_000_000)  # a million agents' float64 column: 8 MB
def frame():
    temporaries = [a * k for k in range(6)]  # alive together, as in an AI step, then all freed
    return sum(t[0] for t in temporaries)
for _ in range(3):
    frame()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    frame()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", FRAMES, mode], capture_output=True, text=True, check=True, timeout=120)
    return int(out.stdout.split()[-1])


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt only")
def test_temporaries_of_a_frame_reuse_the_memory_freed_by_the_last():
    default = _faults("default")
    if default < 10_000:
        pytest.skip(f"this glibc keeps the memory by itself ({default} page faults in 20 frames)")
    kept = _faults("keep")
    # 20 frames of 48 MB of temporaries faulted in afresh would be about 20 x 12,000 pages.
    assert kept < 1_000, f"{kept} page faults in 20 frames with the memory kept ({default} without)"
