"""Headless smoke mode: the whole frame loop offscreen through EGL, a PNG of the last frame and a JSON
of stats. CI runs it on Mesa llvmpipe; the H100 host runs it on the NVIDIA driver.

Frame time is wall-clock per frame with a glFinish at its end, so it includes the GPU's work (a
windowed loop would overlap frames instead; this mode measures, it does not present).
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path

import moderngl
import numpy as np

from .gl import describe, headless_context
from .gltf_write import atomic_write_bytes
from .images import write_png
from .pipeline import CrowdPipeline, PipelineConfig, percentiles

FIXED_DT = 1.0 / 30.0  # headless frames advance a fixed step, so a seed gives the same pictures


def offscreen_framebuffer(ctx: moderngl.Context, size: tuple[int, int]):
    color = ctx.renderbuffer(size, 4)
    depth = ctx.depth_renderbuffer(size)
    return ctx.framebuffer(color_attachments=[color], depth_attachment=depth), (color, depth)


def read_image(framebuffer: moderngl.Framebuffer, size: tuple[int, int]) -> np.ndarray:
    data = framebuffer.read(components=3, alignment=1)
    return np.frombuffer(data, np.uint8).reshape(size[1], size[0], 3)[::-1].copy()


def write_stats(path: Path, stats: dict) -> None:
    atomic_write_bytes(Path(path), (json.dumps(stats, indent=2) + "\n").encode())


def collect_stats(ctx: moderngl.Context, pipeline: CrowdPipeline, frame_ms: list, size, config) -> dict:
    """The stats JSON of a run (headless or windowed): device, frame times, passes and the pipeline's own."""
    stats = describe(ctx)
    stats.update({
        "agents": pipeline.agents,
        "frames": len(frame_ms),
        "size": list(size),
        "seed": pipeline.config.seed,
        "model": str(config.model) if config.model else "built-in zombie",
        "frame_ms": percentiles(frame_ms[1:] if len(frame_ms) > 1 else frame_ms),  # frame 0 compiles shaders
        "nan_count": pipeline.processor.nan_rows(),
        "python": platform.python_version(),
        "moderngl": moderngl.__version__,
        "warnings": pipeline.character.warnings + pipeline.bake.warnings + pipeline.role_notes,
    })
    stats.update(pipeline.stats())
    return stats


def run_headless(config: PipelineConfig, frames: int, size: tuple[int, int], screenshot: Path | None = None,
                 stats_path: Path | None = None, ctx: moderngl.Context | None = None, camera=None) -> dict:
    own_ctx = ctx is None
    ctx = ctx or headless_context()
    pipeline = None
    fb, attachments = offscreen_framebuffer(ctx, size)
    try:
        pipeline = CrowdPipeline(ctx, config)
        pipeline.camera = camera if camera is not None else pipeline.default_camera(size[0] / size[1])
        frame_ms = []
        for _ in range(frames):
            t0 = time.perf_counter()
            pipeline.frame(fb, FIXED_DT)
            ctx.finish()
            frame_ms.append((time.perf_counter() - t0) * 1e3)
        pipeline.timer.end_frame(drain=True)
        image = read_image(fb, size)
        stats = collect_stats(ctx, pipeline, frame_ms, size, config)
        stats["gpu_bytes"]["framebuffer"] = size[0] * size[1] * 8
        if screenshot is not None:
            write_png(screenshot, image)
        if stats_path is not None:
            write_stats(stats_path, stats)
        stats["_image"] = image  # for callers in Python (tests); never written to the JSON
        return stats
    finally:
        if pipeline is not None:
            pipeline.release()
        fb.release()
        for a in attachments:
            a.release()
        if own_ctx:
            ctx.release()
