"""Headless smoke mode: the whole frame loop offscreen through EGL, a PNG of the last frame and a JSON
of stats. CI runs it on Mesa llvmpipe; the H100 host runs it on the NVIDIA driver.

Two frame times, each over its half of the run (the simulation advances a fixed step whatever the
timing, so the pictures do not depend on it):
- the frame period (``frame_period_ms``): frames issued back to back as a swapping window does, the
  CPU at most FRAMES_IN_FLIGHT frames ahead of the GPU (a fence per frame stands in for the swap
  chain), one finish at the end; the interval from one frame's start to the next is what a window's
  frame rate is;
- the frame latency (``frame_latency_ms``): one finish per frame, so each frame's CPU and GPU work
  end to end.
Both drop the run's first frame, which compiles shaders and sizes buffers.
"""

from __future__ import annotations

import time
from collections import deque
from contextlib import nullcontext
from pathlib import Path

import moderngl

from .gl import Fence, Offscreen, headless_context
from .images import write_animation, write_png
from .progress import bar
from .pipeline import CrowdPipeline
from .pipeline_config import PipelineConfig
from .stats import collect_stats, write_stats

FIXED_DT = 1.0 / 30.0  # headless frames advance a fixed step, so a seed gives the same pictures
CLIP_FRAMES = 90  # a clip's frames: the run's last 3 seconds
FRAMES_IN_FLIGHT = 2  # how far a double-buffered swap chain lets the CPU run ahead of the GPU


def paced_frames(ctx: moderngl.Context, frame, count: int, in_flight: int = FRAMES_IN_FLIGHT) -> list[float]:
    """Run `frame()` `count` times back to back, waiting only for the frame `in_flight` frames back
    (as a swap would), then finish once. Returns the intervals (ms) between successive frame starts,
    the last one ending at the finish: the frame period of each frame."""
    fences: deque = deque()
    starts = []
    try:
        for _ in range(count):
            starts.append(time.perf_counter())
            if len(fences) == in_flight:
                fence = fences.popleft()
                fence.wait()
                fence.release()
            frame()
            fences.append(Fence())
        ctx.finish()
        starts.append(time.perf_counter())
    finally:
        for fence in fences:
            fence.release()
    return [(b - a) * 1e3 for a, b in zip(starts, starts[1:])]


def run_headless(config: PipelineConfig, frames: int, size: tuple[int, int], screenshot: Path | None = None,
                 stats_path: Path | None = None, ctx: moderngl.Context | None = None, camera=None, overlay=None,
                 clip: Path | None = None) -> dict:
    """`camera`: a Camera, or the name of one of the crowd's views (crowd.cameras.view_camera; None: "auto").
    `overlay`: drawn over every frame, as a window draws its panel: called as overlay(ctx, pipeline, size)
    once the pipeline exists, it gives a GL stage with draw(framebuffer, dt), released when the run ends.
    `clip`: the run's last CLIP_FRAMES frames written there as an animated WebP or GIF (crowd.images; each
    frame is read back, so the run's timings then include that)."""
    own_ctx = ctx is None
    ctx = ctx or headless_context()
    try:
        with Offscreen(ctx, size) as target, CrowdPipeline(ctx, config) as pipeline:
            named = camera is None or isinstance(camera, str)
            pipeline.camera = pipeline.view_camera(camera or "auto", size[0] / size[1]) if named else camera
            with (overlay(ctx, pipeline, size) if overlay is not None else nullcontext()) as drawn_over, \
                    bar(frames, f"{config.agents:,} agents", "frame") as shown:  # on a terminal only (crowd.progress)

                frames_seen, done = [], [0]

                def frame():
                    pipeline.frame(target.framebuffer, FIXED_DT)
                    if drawn_over is not None:
                        drawn_over.draw(target.framebuffer, FIXED_DT)
                    done[0] += 1
                    if clip is not None and done[0] > frames - CLIP_FRAMES:  # only the frames the clip keeps are read back
                        frames_seen.append(target.image())
                    shown.update(1)

                period_ms = paced_frames(ctx, frame, frames // 2)
                latency_ms = []
                for _ in range(frames - frames // 2):
                    t0 = time.perf_counter()
                    frame()
                    ctx.finish()
                    latency_ms.append((time.perf_counter() - t0) * 1e3)
            pipeline.timer.end_frame(drain=True)
            pipeline.refresh_counts()  # the GPU cull's counts trail: these are the last frame's
            image = target.image()
            # The run's first frame compiles shaders: it is dropped from whichever half holds it.
            stats = collect_stats(ctx, pipeline, {"frame_period_ms": period_ms[1:] if len(period_ms) > 1 else period_ms,
                                                  "frame_latency_ms": latency_ms[1:] if not period_ms and len(latency_ms) > 1 else latency_ms},
                                  size, config, frames)
        stats["gpu_bytes"]["framebuffer"] = size[0] * size[1] * 8
        if screenshot is not None:
            write_png(screenshot, image)
        if clip is not None:
            stats["clip_bytes"] = write_animation(clip, frames_seen, 1.0 / FIXED_DT)
        if stats_path is not None:
            write_stats(stats_path, stats)
        stats["_image"] = image  # for callers in Python (tests); never written to the JSON
        return stats
    finally:
        if own_ctx:
            ctx.release()
