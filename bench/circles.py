"""``crowd-bench circles``: FLAME GPU 2's "circles" benchmark on this project's GPU grid
(crowd.sim.gpu.grid, the one the AI's separation reads), against the figures FLAME GPU 2 publishes.

Their workload: a million agents in 3D at a density of 1 per unit volume, a radius of 2, each reading
the messages of the 27 cells around it (about 204 neighbours), 200 steps: 1.84 ms a step on an H100
NVL with run-time compilation, 2.27 ms without. Our grid is 2D (a crowd walks on the ground), so the
workload here is the 2D one that reads as many: cells one radius wide, 9 of them around an agent, at
the density that puts `read` agents in them (204 / (9 x 2 x 2) = 5.67 a unit area). Each step builds
the grid (the counting sort and the per-cell order) and moves every agent; two runs from the same start
are compared bit for bit."""

from __future__ import annotations

import contextlib
import json
import math
import time
from pathlib import Path

import numpy as np

FLAME_GPU_MS = {"H100 NVL, run-time compiled": 1.84, "H100 NVL, plain": 2.27}  # their published ms a step at 1M agents
RADIUS = 2.0
REPULSE = 0.05


def bench_circles(args) -> int:
    import moderngl

    from crowd.gl import describe, headless_context, load_shader
    from crowd.sim.gpu.grid import GROUP, SHADER_STORAGE, NeighbourGrid
    from crowd.sim.separation import grid_shape

    from .ai_report import PassQueries

    ctx = headless_context(430)
    info = describe(ctx)
    device = f"{info['gl_renderer']}, {info['gl_version']}; moderngl {moderngl.__version__}"
    n = int(args.agents)
    density = args.read / (9.0 * RADIUS * RADIUS)
    extent = math.sqrt(n / density)
    size, side = grid_shape(0.5 * extent, RADIUS, n)
    print(f"{device} | {n:,} agents, 2D, radius {RADIUS}, density {density:.3f} a unit area ({args.read:g} read an agent), "
          f"{args.steps} steps, {side}x{side} cells")
    start = np.zeros((n, 4), np.float32)
    start[:, :2] = np.random.default_rng(1).uniform(0.0, extent, (n, 2))
    program = ctx.compute_shader(load_shader("bench/circles.comp.glsl"))
    program["u_n"].value, program["u_side"].value, program["u_radius"].value = n, side, RADIUS
    program["u_repulse"].value, program["u_extent"].value = REPULSE, extent
    groups = (n + GROUP - 1) // GROUP
    query = ctx.query(time=True)
    runs = []
    with NeighbourGrid(ctx, live_only=False) as grid:
        for run in range(2):
            points = [ctx.buffer(start.tobytes()), ctx.buffer(reserve=start.nbytes)]

            def step(k: int, timer=None) -> None:
                grid.build(points[k % 2], n, (0.0, 0.0), size, side, timer)
                points[k % 2].bind_to_storage_buffer(0)
                points[(k + 1) % 2].bind_to_storage_buffer(15)
                with timer.gpu("move") if timer is not None else contextlib.nullcontext():
                    program.run(groups)
                    ctx.memory_barrier(SHADER_STORAGE)

            ctx.finish()
            t = time.perf_counter()
            for k in range(args.steps):
                step(k)
            ctx.finish()
            period = (time.perf_counter() - t) / args.steps
            final = points[args.steps % 2].read()
            out = np.frombuffer(final, np.float32).reshape(n, 4)
            gpu_ms = []
            for k in range(args.steps, args.steps + 20):  # the GPU's own time for a step, after the timed run
                with query:
                    step(k)
                gpu_ms.append(query.elapsed * 1e-6)
            passes = PassQueries(ctx)
            for k in range(args.steps + 20, args.steps + 40):
                step(k, passes)
            passes.release()
            runs.append({"period_ms": period * 1e3, "gpu_ms": float(np.median(gpu_ms)), "bytes": final, "passes": passes.medians(),
                         "read": float(out[:, 2].mean()), "drift": float(out[:, 3].mean())})
            for b in points:
                b.release()
    program.release()
    same = runs[0]["bytes"] == runs[1]["bytes"]
    row = {"agents": n, "steps": args.steps, "dimensions": 2, "radius": RADIUS, "density": density, "cells": side * side,
           "read_per_agent": round(runs[0]["read"], 1), "ms_per_step": [round(r["period_ms"], 4) for r in runs],
           "gpu_ms_per_step": [round(r["gpu_ms"], 4) for r in runs], "deterministic": same, "device": device,
           "flame_gpu_2_ms": FLAME_GPU_MS, "passes_ms": runs[0]["passes"]}
    print(f"ms a step (period of {args.steps} steps, one finish): {row['ms_per_step']} | GPU timer: {row['gpu_ms_per_step']} | "
          f"read {row['read_per_agent']} an agent | bit-identical runs: {same}")
    print("passes (GPU ms, run 1): " + " ".join(f"{k} {v:.4f}" for k, v in row["passes_ms"].items()))
    print("FLAME GPU 2 (3D, published): " + ", ".join(f"{k}: {v} ms" for k, v in FLAME_GPU_MS.items()))
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps(row, indent=1).encode())
    return 0 if same else 1
