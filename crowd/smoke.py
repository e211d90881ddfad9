"""Headless smoke mode: the whole frame loop offscreen through EGL, a PNG of the last frame and a JSON
of stats. CI runs it on Mesa llvmpipe; the H100 host runs it on the NVIDIA driver.

Frame time is wall-clock per frame with a glFinish at its end, so it includes the GPU's work (a
windowed loop would overlap frames instead; this mode measures, it does not present).
"""

from __future__ import annotations

import time
from pathlib import Path

import moderngl

from .gl import Offscreen, headless_context
from .images import write_png
from .pipeline import CrowdPipeline, PipelineConfig
from .stats import collect_stats, write_stats

FIXED_DT = 1.0 / 30.0  # headless frames advance a fixed step, so a seed gives the same pictures


def run_headless(config: PipelineConfig, frames: int, size: tuple[int, int], screenshot: Path | None = None,
                 stats_path: Path | None = None, ctx: moderngl.Context | None = None, camera=None) -> dict:
    own_ctx = ctx is None
    ctx = ctx or headless_context()
    try:
        with Offscreen(ctx, size) as target, CrowdPipeline(ctx, config) as pipeline:
            pipeline.camera = camera if camera is not None else pipeline.default_camera(size[0] / size[1])
            frame_ms = []
            for _ in range(frames):
                t0 = time.perf_counter()
                pipeline.frame(target.framebuffer, FIXED_DT)
                ctx.finish()
                frame_ms.append((time.perf_counter() - t0) * 1e3)
            pipeline.timer.end_frame(drain=True)
            image = target.image()
            stats = collect_stats(ctx, pipeline, frame_ms, size, config)
        stats["gpu_bytes"]["framebuffer"] = size[0] * size[1] * 8
        if screenshot is not None:
            write_png(screenshot, image)
        if stats_path is not None:
            write_stats(stats_path, stats)
        stats["_image"] = image  # for callers in Python (tests); never written to the JSON
        return stats
    finally:
        if own_ctx:
            ctx.release()
