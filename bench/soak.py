"""``crowd-bench soak``: the game as shipped (the default scene: the mixed horde, the town, the scripted
survivor with its rounds) run headless for many frames, checking that nothing grows or goes wrong.

After a warm-up, every `every` frames it samples the process's resident memory (/proc/self/statm) and
the count of live GL objects by kind (glIs* over the names the driver hands out), and it logs a fault
for: a palette row with NaN or Inf, a GL error, an exception, a Python warning or a log record at
WARNING or above. For each measure it reports the range of its samples, the drift (the median of the
last quarter of the samples against that of the first quarter: growth) and the spread (the range
against the same); the issue's limit is 2 %.

The memory is sampled twice: as it is, and after glibc's malloc_trim. Untrimmed, llvmpipe's threads
left one-off steps of 20 MB in the allocator's free lists (a step, then flat), which read as growth.
Trimmed, Mesa's llvmpipe swings the resident memory by about 10 % from frame to frame at 300 agents
(the Python heap, traced, holds within 1.5 MB), hence the quartile medians for the drift. The swing is
between two levels (212 and 238 MB in two runs of the short soak: a block the driver takes and gives
back), so the quartiles' medians land on either and the drift read -5.9 % and +3.8 % in two runs of one
tree; the growth, the rise of the samples' floor or ceiling from the first half to the second, is what a
leak moves whichever level the samples land on. Even that read 12 % in one of three runs of one tree in
one process, where the driver's level changed once for good in the second half (223 to 261 MB). So the
short soak's leak check is the Python heap, traced (``heap``: 0.0 to 1.1 MB held after the warm-up, its
rise 0.29 and 0.49 MB in two runs), with the resident memory as a check on gross growth only.
"""

from __future__ import annotations

import ctypes
import logging
import os
import time
import tracemalloc
import warnings

import numpy as np

GL_KINDS = ("Buffer", "Texture", "Program", "Shader", "VertexArray", "Framebuffer", "Renderbuffer", "Sampler")
_DELETE_STATUS = 0x8B80
NAMES_SEARCHED = 4096  # GL names are small integers handed out from 1 and reused; this covers every run here


class SoakError(ValueError):
    """Soak settings that cannot run; the message is one line."""


def gl_census() -> dict[str, set[int]]:
    """The GL object names alive in the current context, by kind. A program or shader that was released
    but is still referenced by the context's state (Mesa keeps the last one bound) reports
    GL_DELETE_STATUS and is not counted: the driver frees it when the state moves on. Queries are left
    out: moderngl 5.13 cannot release them, and the pass timer reuses a fixed ring of them."""
    from crowd.gl import current_context_function

    int_out = ctypes.CFUNCTYPE(None, ctypes.c_uint, ctypes.c_uint, ctypes.POINTER(ctypes.c_int))
    deleted = {"Program": current_context_function("glGetProgramiv", int_out), "Shader": current_context_function("glGetShaderiv", int_out)}
    out = {}
    for kind in GL_KINDS:
        is_kind = current_context_function(f"glIs{kind}", ctypes.CFUNCTYPE(ctypes.c_ubyte, ctypes.c_uint))
        names = {name for name in range(1, NAMES_SEARCHED) if is_kind(name)}
        if kind in deleted:
            status = ctypes.c_int(0)
            names = {n for n in names if not (deleted[kind](n, _DELETE_STATUS, ctypes.byref(status)) or status.value)}
        out[kind] = names
    return out


def resident_bytes(trim: bool = False) -> int:
    """The process's resident set now (not its peak), from /proc (Linux). `trim`: first hand the C heap's
    free pages back to the system (glibc's malloc_trim), so the figure is what the process holds, not
    what the allocator keeps for later (one-off steps of tens of MB, seen on llvmpipe's threads)."""
    if trim:
        try:
            ctypes.CDLL("libc.so.6").malloc_trim(0)
        except (OSError, AttributeError):  # not glibc: the untrimmed figure
            pass
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


class _Faults(logging.Handler):
    def __init__(self):
        super().__init__(logging.WARNING)
        self.records: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(f"log {record.name}: {record.getMessage()}")


def run_soak(agents: int, frames: int, size: tuple[int, int], warmup: int, every: int, scene_path=None, seed: int = 1,
             progress=None, on_sample=None, heap: bool = False) -> dict:
    """Run the soak; returns its samples, figures and faults (see the module's docstring). `on_sample`
    is called with the samples so far after each one (the command line keeps a partial JSON). With `heap`,
    the Python heap (numpy's arrays included) is traced from a sample's span before the warm-up's end,
    and each sample holds what of it is still allocated (tracemalloc: slower, and exact where the
    resident memory is not)."""
    from crowd.gl import Offscreen, describe, headless_context
    from crowd.pipeline import CrowdPipeline
    from crowd.scene import Scene, load_scene
    from crowd.smoke import FIXED_DT

    if not 0 < warmup < frames or every < 1:
        raise SoakError(f"soak: need 0 < warmup < frames and every >= 1, got warmup {warmup}, frames {frames}, every {every}")
    scene = (load_scene(scene_path) if scene_path else Scene()).with_overrides(agents=agents, seed=seed)
    faults: list[str] = []
    handler = _Faults()
    logging.getLogger().addHandler(handler)
    samples = []
    ctx = headless_context()
    started = time.perf_counter()
    try:
        info = describe(ctx)
        with warnings.catch_warnings(record=True) as caught, Offscreen(ctx, size) as target, \
                CrowdPipeline(ctx, scene.pipeline_config()) as pipeline:
            warnings.simplefilter("always")
            pipeline.camera = scene.camera_for(size[0] / size[1]) or pipeline.default_camera(size[0] / size[1])
            for frame in range(frames):
                try:
                    pipeline.frame(target.framebuffer, FIXED_DT)
                except Exception as exc:  # a fault to report, not a crash of the soak
                    faults.append(f"frame {frame}: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}")
                    break
                if progress is not None:
                    progress.update(1)
                if heap and frame + 1 == max(warmup - every, 1):  # (a sample's span before the first: it starts at a steady state)
                    tracemalloc.start()
                if frame + 1 >= warmup and (frame + 1 - warmup) % every == 0:
                    ctx.finish()
                    error = ctx.error
                    if error != "GL_NO_ERROR":
                        faults.append(f"frame {frame}: {error}")
                    nan = pipeline.processor.nan_rows()
                    if nan:
                        faults.append(f"frame {frame}: {nan} palette rows with NaN or Inf")
                    counts = {kind: len(names) for kind, names in gl_census().items()}
                    samples.append({"frame": frame + 1, "rss_untrimmed_bytes": resident_bytes(), "rss_bytes": resident_bytes(trim=True), "gl_objects": sum(counts.values()),
                                    "gl_by_kind": counts, "agents": pipeline.agents, "seconds": round(time.perf_counter() - started, 1),
                                    "round": pipeline.survivor.rounds if pipeline.survivor is not None else None,
                                    **({"heap_bytes": tracemalloc.get_traced_memory()[0]} if heap else {})})
                    if on_sample is not None:
                        on_sample(samples)
            faults += [f"warning {w.category.__name__}: {w.message}" for w in caught]
    finally:
        if heap:
            tracemalloc.stop()
        logging.getLogger().removeHandler(handler)
        ctx.release()
    faults += handler.records
    rss = _figures([s["rss_bytes"] / 2**20 for s in samples])
    untrimmed = _figures([s["rss_untrimmed_bytes"] / 2**20 for s in samples])
    gl = _figures([s["gl_objects"] for s in samples])
    traced = _figures([s["heap_bytes"] / 2**20 for s in samples]) if heap else None
    return {"device": f"{info['gl_renderer']}, {info['gl_version']}", "agents": agents, "frames": frames, "size": list(size),
            "warmup": warmup, "every": every, "scene": str(scene_path or "default"), "seconds": round(time.perf_counter() - started, 1),
            "rss_mb": rss, "rss_untrimmed_mb": untrimmed, "heap_mb": traced, "gl_objects": gl, "rounds": samples[-1]["round"] if samples else None, "faults": faults, "samples": samples}


def _figures(values: list[float]) -> dict | None:
    """A sampled measure after the warm-up: its range, and its drift, the change from the median of the
    first quarter of the samples to that of the last quarter, as a share of the first (growth over the
    run, where one sample's transient native allocations would read as noise), its spread, the range as
    a share of the same, and its growth, the larger rise of the floor and of the ceiling from the first
    half of the samples to the second, as a share of the same."""
    if not values:
        return None
    quarter = max(1, len(values) // 4)
    first, last = float(np.median(values[:quarter])), float(np.median(values[-quarter:]))
    half = max(1, len(values) // 2)
    early, late = values[:half], values[half:] or values[-1:]
    growth = max(min(late) - min(early), max(late) - max(early))
    return {"first": round(first, 2), "last": round(last, 2), "min": round(min(values), 2), "max": round(max(values), 2),
            "drift": (last - first) / first if first else 0.0, "spread": (max(values) - min(values)) / first if first else 0.0,
            "growth": growth / first if first else 0.0, "rise": round(growth, 4)}
