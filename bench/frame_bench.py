"""``crowd-bench frame``: the whole headless frame (AI, processor, culling, shadows, draws, weapons) as a
window runs it: its period, latency, CPU time, GL calls and GPU passes against agent count."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np

from crowd.progress import steps

from .common import device_cpu

GL_COUNT_FRAMES = 10  # frames whose GL calls are counted (after the timed ones)


def bench_frame(args) -> int:
    """The whole headless frame (AI, processor, culling, shadows, draws, weapons) as a window runs it.
    Period: `frames` frames issued back to back with one finish at the end, the CPU at most 2 frames
    ahead of the GPU as a swapping window is (crowd.smoke.paced_frames), divided by `frames` (what a
    window's frame rate is); the per-frame intervals give its p95 and max. Latency: one finish per frame. Both after a warm-up, `repeats` times; the
    pass medians come from the same frames (GPU passes from timer queries)."""
    import moderngl

    from bench.gl_calls import counting_gl_calls
    from crowd.gl import Offscreen, describe, headless_context
    from crowd.pipeline import CrowdPipeline
    from crowd.scene import Scene, load_scene
    from crowd.settings import parse
    from crowd.smoke import FIXED_DT, paced_frames

    if args.panel:
        from app.overlay import HeadlessPanel
    dt = FIXED_DT if args.dt is None else args.dt

    size = parse("size", args.size)
    # The default scene on the empty plane (the benchmarks' ground since before the town); a scene file decides for itself.
    scene = load_scene(args.scene) if args.scene else Scene(town=False)
    ctx = headless_context()
    info = describe(ctx)
    device = f"{info['gl_renderer']}, {info['gl_version']}; {device_cpu()}; moderngl {moderngl.__version__}"
    print(f"{device} | {size[0]}x{size[1]} | {args.frames} frames per period, {args.repeats} repeats")
    print(f"{'agents':>15} {'ai':>4} {'period ms':>10} {'latency ms':>11} {'fps':>7} {'call ms':>7} {'CPU ms':>7} {'GL calls':>8} {'GPU sum':>8}  biggest passes (median ms)")
    rows = []
    with Offscreen(ctx, size) as target:
        cases = [(n, panel, path) for n in [int(x) for x in args.agents.split(",")] for panel in ((False, True) if args.panel else (False,))
                 for path in args.ai_path.split(",")]
        for n, panel, path in steps(cases, desc="frame", unit="case"):
            config = scene.with_overrides(agents=n, workers=args.workers, ai_path=path).pipeline_config()
            with CrowdPipeline(ctx, config) as pipeline, \
                    (HeadlessPanel(ctx, pipeline, size, scene) if panel else contextlib.nullcontext()) as overlay:
                start = pipeline.camera = scene.camera_for(size[0] / size[1]) or pipeline.overview_camera(size[0] / size[1])
                turned = [0]

                def frame():
                    if args.orbit:  # (every frame's camera and light constants change, as a following camera's do)
                        turned[0] += 1
                        pipeline.camera = orbited(start, math.radians(args.orbit) * turned[0])
                    pipeline.frame(target.framebuffer, dt)
                    if overlay is not None:  # the panel and HUD, as the window draws them
                        overlay.draw(target.framebuffer, dt)

                for _ in range(args.warmup):
                    frame()
                ctx.finish()
                periods, latencies, intervals, cpu, calls = [], [], [], [], []

                def timed_frame():  # the CPU's own time issuing a frame (waits on the GPU are outside it)
                    c = time.perf_counter()
                    frame()
                    calls.append((time.perf_counter() - c) * 1e3)

                for _ in range(args.repeats):
                    c0 = time.thread_time()
                    paced = paced_frames(ctx, timed_frame, args.frames)
                    cpu.append((time.thread_time() - c0) * 1e3 / args.frames)  # the main thread's CPU time a frame
                    periods.append(sum(paced) / len(paced))
                    intervals += paced
                    for _ in range(max(1, args.frames // 2)):
                        t0 = time.perf_counter()
                        frame()
                        ctx.finish()
                        latencies.append((time.perf_counter() - t0) * 1e3)
                frame_cpu = float(np.median(pipeline.cpu_ms.recent(args.frames * args.repeats)))  # (the timed frames' own CPU inside frame())
                with counting_gl_calls() as gl:  # (after the timed frames: the counting costs CPU itself)
                    for _ in range(GL_COUNT_FRAMES):
                        frame()
                gl_calls = {k: round(v / GL_COUNT_FRAMES, 2) for k, v in gl.most_common()}
                profile = _profile_frames(frame, args.profile) if args.profile else None
                pipeline.timer.end_frame(drain=True)
                passes = pipeline.timer.medians()
                ctx.finish()
                alone = _replay_gpu_passes(ctx, pipeline, target.framebuffer, args.frames)
                pipeline.refresh_counts()
                drawn = dict(pipeline.renderer.last)
                weapons = dict(pipeline.weapons.last) if pipeline.weapons is not None else None
                memory = pipeline.gpu_bytes()
                cull = pipeline.renderer.cull_path
                ai_processes = pipeline.ai.ranges()
                ai_path, bytes_ = pipeline.ai_path, pipeline.frame_bytes()
            gpu_sum = sum(v for k, v in passes.items() if pipeline.timer.clock.get(k) == "gpu")
            row = {"agents": n, "panel": panel, "ai_path": ai_path, **bytes_, "cpu_ms": round(float(np.median(cpu)), 3),
                   "frame_cpu_ms": round(frame_cpu, 3), "gl_calls": round(sum(gl_calls.values()), 1), "gl_calls_by_kind": gl_calls,
                   "frame_call_ms": round(float(np.median(calls)), 3), "gpu_passes_sum_ms": round(float(gpu_sum), 3),
                   "gpu_passes_alone_sum_ms": round(float(sum(alone.values())), 3), "cull": cull, "ai_processes": ai_processes, "drawn": drawn, "weapons": weapons, "gpu_bytes": memory, "period_ms": round(float(np.median(periods)), 3), "periods_ms": [round(p, 3) for p in periods],
                   "frame_period_ms": {"p50": round(float(np.percentile(intervals, 50)), 3), "p95": round(float(np.percentile(intervals, 95)), 3),
                                       "max": round(float(np.max(intervals)), 3)},
                   "latency_ms": round(float(np.median(latencies)), 3), "passes_ms": passes, "gpu_passes_alone_ms": alone}
            if profile is not None:
                row["profile"] = profile
            rows.append(row)
            top = sorted(passes.items(), key=lambda kv: -kv[1])[:4]
            print(f"{n:>8}{' +panel' if panel else '':7} {ai_path:>4} {row['period_ms']:>10.2f} {row['latency_ms']:>11.2f} {1e3 / row['period_ms']:>7.1f} "
                  f"{row['frame_call_ms']:>7.2f} {row['frame_cpu_ms']:>7.2f} {row['gl_calls']:>8.0f} {row['gpu_passes_sum_ms']:>8.2f}  "
                  + ", ".join(f"{k} {v:.2f}" for k, v in top))
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps({"device": device, "size": list(size), "scene": str(args.scene or "default"),
                                                        "dt_s": dt, "orbit_deg_per_frame": args.orbit, "rows": rows}, indent=1).encode())
    ctx.release()
    return 0


def orbited(camera, radians: float):
    """`camera` turned about its target's vertical axis by `radians`."""
    eye, target = np.asarray(camera.eye, np.float64), np.asarray(camera.target, np.float64)
    c, s = math.cos(radians), math.sin(radians)
    d = eye - target
    return dataclasses.replace(camera, eye=tuple(target + (c * d[0] - s * d[2], d[1], s * d[0] + c * d[2])))


def _profile_frames(frame, count: int, top: int = 40) -> dict:
    """cProfile over `count` frames (after the timed ones: the profiler slows Python down): the functions
    with the most time of their own, ms a frame, and each one's time with its callees."""
    import cProfile
    import pstats

    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(count):
        frame()
    profiler.disable()
    stats = pstats.Stats(profiler).stats
    rows = sorted(stats.items(), key=lambda kv: -kv[1][2])[:top]
    return {"frames": count, "total_ms": round(sum(v[2] for v in stats.values()) * 1e3 / count, 3),
            "by_own_ms": [{"function": f"{Path(file).name}:{line}({name})" if file != "~" else name, "calls": v[1] / count,
                           "own_ms": round(v[2] * 1e3 / count, 4), "with_callees_ms": round(v[3] * 1e3 / count, 4)}
                          for (file, line, name), v in rows]}


def _replay_gpu_passes(ctx, pipeline, framebuffer, count: int) -> dict:
    """The last frame's shadow, draw and weapons passes replayed `count` times back to back (the same
    lists and commands), each timed with a timer query: their GPU time with the GPU kept busy. In the
    frame the GPU idles while the CPU runs the AI, and the H200 then sits at lower clocks: the same draw
    read 10.8 to 20.8 ms at 100,000 agents from one run to the next (docs/BENCHMARKS.md). The splat of the
    smallest impostors (crowd.draw.splat) is not replayed: it sorts the lists it reads, so the replayed
    draw is its quads alone; the splat's time is the frame's."""
    from crowd.timing import PassTimer

    view, renderer, weapons = pipeline.last.view, pipeline.renderer, pipeline.weapons
    if view is None or not pipeline.agents:
        return {}
    with PassTimer(ctx) as timer:
        for k in range(count + 10):  # 10 to bring the clocks up, then `count` timed
            if renderer.shadows:
                with timer.gpu("shadow"):
                    renderer.shadow_pass(view, pipeline.processor)
                    if weapons is not None and weapons.casts_shadows():
                        weapons.depth_pass(view, renderer)
            with timer.gpu("draw"):
                renderer.color_pass(framebuffer, view, pipeline.processor)
            if weapons is not None and weapons.last["weapons"]:
                with timer.gpu("weapons"):
                    weapons.color_pass(framebuffer, view, renderer)
            timer.end_frame()
            if k == 9:
                timer.end_frame(drain=True)
                timer.samples.clear()  # the warm-up frames are not counted
        timer.end_frame(drain=True)
        out = timer.medians()
    out["sum"] = round(sum(out.values()), 3)
    return out
