"""``crowd-bench ai``: ms per crowd-AI step against agent count, for the numpy AI on the CPU (its
processes, its think budget, the town) and the compute passes on the GPU (crowd.sim.gpu), side by side
in one run. A step is one 1/60 s substep and the processor's layers written, as the frame does."""

from __future__ import annotations

import contextlib
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from crowd.progress import steps

from .common import device_cpu


def bench_ai(args) -> int:
    from crowd.allocator import keep_freed_memory
    from crowd.anim.roles import bake_roles, match_roles
    from crowd.asset.gltf import load_character
    from crowd.sim.agent_pool import available_cores
    from crowd.sim.config import AIConfig
    from crowd.sim.motion import motion_for

    keep_freed_memory()  # as the frame loop runs (crowd.allocator)
    character = load_character(args.model)
    roles, _ = match_roles(character.clips)
    motion = motion_for(character, bake_roles(character, roles), roles)
    device = device_cpu()
    paths = [p.strip() for p in args.path.split(",")]
    if any(p not in ("cpu", "gpu") for p in paths):
        print(f"crowd-bench: --path takes cpu and gpu, got {args.path!r}", file=sys.stderr)
        return 2
    agents = [int(x) for x in args.agents.split(",")]
    print(f"{device} | {available_cores()} cores to run on | median of {args.steps} steps after {args.warmup} warm-up steps of 1/60 s")
    result = {"device": device, "rows": []}
    if "cpu" in paths:
        budgets = [int(k) for k in args.think_every.split(",")] if args.think_every else [AIConfig().think_every]
        pools = [int(k) for k in args.workers.split(",")] if args.workers else [AIConfig().workers]
        towns = [False, True] if args.town else [False]
        obstacles = None
        if args.town:
            from crowd.asset.town import build_town

            obstacles = build_town().obstacles()
        rows = bench_cpu(args, motion, [(n, k, w, town) for n in agents for k in budgets for w in pools for town in towns], obstacles)
        if isinstance(rows, int):
            return rows
        result["rows"] += rows
    if "gpu" in paths:
        town = None
        if args.town:
            from crowd.asset.town import build_town

            town = build_town().obstacles()
        rows, gpu = bench_gpu(args, motion, agents, town)
        result["rows"] += rows
        result["gpu"] = gpu
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps(result, indent=1).encode())
    return 0


class PassQueries:
    """GPU ms of each named pass, from a timer query read at once (a profile: it waits for each pass)."""

    def __init__(self, ctx):
        self.query, self.times = ctx.query(time=True), {}

    @contextlib.contextmanager
    def gpu(self, name: str):
        with self.query:
            yield
        self.times.setdefault(name, []).append(self.query.elapsed * 1e-6)

    def medians(self) -> dict:
        return {name: round(float(np.median(v)), 4) for name, v in self.times.items()}

    def release(self) -> None:
        self.query.release() if hasattr(self.query, "release") else None


def bench_gpu(args, motion, agents: list[int], town=None) -> tuple[list, str]:
    """The compute passes: per agent count, the GPU's own time for a step (a timer query around it, the
    median), the period of steps issued back to back with one finish at the end, and the CPU's ms to
    issue a step. The crowd starts from the numpy AI's spawn; the player walks the headless circle and
    strikes the nearest zombie every 0.9 s, on the GPU."""
    import moderngl

    from crowd.gl import describe, headless_context
    from crowd.sim.ai import CrowdAI
    from crowd.sim.config import AIConfig
    from crowd.sim.gpu.ai import GpuCrowdAI

    ctx = headless_context(430)
    info = describe(ctx)
    gpu = f"{info['gl_renderer']}, {info['gl_version']}; moderngl {moderngl.__version__}"
    print(f"GPU path: {gpu}")
    print(f"{'agents':>8} {'GPU ms/step':>12} {'period ms':>10} {'CPU ms':>7} {'same':>6} {'chasing':>8}  passes alone (GPU ms)")
    rows = []
    query = ctx.query(time=True)
    for n, obstacles in steps([(n, o) for n in agents for o in ((None, town) if town is not None else (None,))], desc="ai gpu", unit="case"):
        ai = CrowdAI(n, args.seed, motion, AIConfig(think_every=1, workers=1), obstacles=obstacles)
        radius = ai.half_extent * 0.5 if obstacles is None else min(ai.half_extent * 0.5, 9.0)  # (PlayerScript.headless's circle)
        layers = ctx.buffer(reserve=max(64 * n, 64))
        with GpuCrowdAI(ctx, ai) as g:
            next_strike = 0.9

            def step() -> None:
                nonlocal next_strike
                angle = g.time * 2.4 / max(radius, 1e-3)
                g.player = g.origin + radius * np.array([math.cos(angle), math.sin(angle)])
                if g.time >= next_strike:
                    next_strike += 0.9
                    g.strike_nearest(g.player, 2.0)
                g.step(1 / 60)
                g.write_layers(layers)

            for _ in range(args.warmup):
                step()
            ctx.finish()
            gpu_ms = []
            for _ in range(args.steps):
                with query:
                    step()
                gpu_ms.append(query.elapsed * 1e-6)
            ctx.finish()
            cpu, t = [], time.perf_counter()
            for _ in range(args.steps):
                c = time.perf_counter()
                step()
                cpu.append(time.perf_counter() - c)
            ctx.finish()
            period = (time.perf_counter() - t) / args.steps
            g.timer = passes = PassQueries(ctx)  # each pass alone, a finish after each: where the step's time goes
            for _ in range(min(args.steps, 50)):
                step()
            g.timer = None
            passes.release()
            counts = g.counts()
            final = g.raw()
        # The same crowd again from the same start, stepped as the timed run was: bit for bit?
        with GpuCrowdAI(ctx, ai) as g:
            next_strike = 0.9
            for _ in range(args.warmup + 2 * args.steps + min(args.steps, 50)):
                step()
            same = g.raw() == final
            new_crowd = _new_crowd_costs(ctx, g, args.seed + 1, motion, obstacles)
        layers.release()
        ai.close()
        row = {"path": "gpu", "town": obstacles is not None, "agents": n, "gpu_ms_per_step": round(float(np.median(gpu_ms)), 4),
               "period_ms": round(period * 1e3, 4), "cpu_ms_per_step": round(float(np.median(cpu)) * 1e3, 4), "states": counts,
               "deterministic": same, "new_crowd": new_crowd,
               "passes_ms": passes.medians()}
        rows.append(row)
        print(f"{n:>8}{' town' if obstacles is not None else '':5} {row['gpu_ms_per_step']:>12.4f} {row['period_ms']:>10.4f} {row['cpu_ms_per_step']:>7.3f} {str(same):>6} {counts['chase']:>8}  "
              + " ".join(f"{k} {v:.4f}" for k, v in row["passes_ms"].items()))
        print(" " * 9 + "a new crowd: " + ", ".join(f"{k} {v}" for k, v in new_crowd.items()))
    query.release() if hasattr(query, "release") else None
    ctx.release()
    return rows, gpu


def _new_crowd_costs(ctx, g, seed: int, motion, obstacles) -> dict:
    """What a new round's crowd costs the frame it starts in, the GPU path's two ways of taking it: the
    numpy AI's spawn (CPU ms, the traits the CPU keeps), and then either its rows sent (bytes, wall ms to
    the GPU having them) or the GPU's own spawn from the same keyed draws (bytes, wall ms, GPU ms)."""
    from crowd.sim.ai import CrowdAI
    from crowd.sim.config import AIConfig

    ctx.finish()
    t = time.perf_counter()
    ai = CrowdAI(g.n, seed, motion, AIConfig(think_every=1, workers=1), obstacles=obstacles)
    out = {"numpy_spawn_ms": round((time.perf_counter() - t) * 1e3, 3)}
    query = ctx.query(time=True)
    for fresh in (False, True):
        g.sent_bytes = 0
        t = time.perf_counter()
        with query:
            g.load(ai, fresh=fresh)
        ctx.finish()
        key = "spawned" if fresh else "rows_sent"
        out[f"{key}_bytes"], out[f"{key}_wall_ms"] = g.sent_bytes, round((time.perf_counter() - t) * 1e3, 3)
        out[f"{key}_gpu_ms"] = round(query.elapsed * 1e-6, 4)
    ai.close()
    return out


def bench_cpu(args, motion, cases, obstacles) -> list | int:
    """The numpy AI: steps a crowd around a scripted player for a warm-up, then times steps. The
    separation's share is the AI's own count of the time it spent there (``CrowdAI.separation_seconds``),
    so the table says what bounds a step."""
    from crowd.sim.ai import CrowdAI, PlayerScript
    from crowd.sim.config import AIConfig

    print(f"{'agents':>8} {'think every':>11} {'workers':>7} {'ms/step':>9} {'mean':>7} {'p95 ms':>8} {'separation':>11} {'list builds':>12} "
          f"{'chasing':>8} {'exact':>6}")
    rows = []
    for n, think_every, workers, town in steps(cases, desc="ai", unit="case"):
        ai = CrowdAI(n, args.seed, motion, AIConfig(think_every=think_every, workers=workers), obstacles=obstacles if town else None)
        # The player's circle, as the headless loop walks it (in a town, round the crossing).
        script = PlayerScript.headless(ai)
        spent = []  # seconds of separation per timed step
        for _ in range(args.warmup):
            script.update(ai)
            ai.step(1 / 60)
        builds = ai.pair_builds
        times = []
        for _ in range(args.steps):
            script.update(ai)
            separation = ai.separation_seconds
            t = time.perf_counter()
            ai.step(1 / 60)
            ai.write_layers()  # into the AI's own array, as the frame does
            times.append(time.perf_counter() - t)
            spent.append(ai.separation_seconds - separation)
        faults = ai.check()
        used = ai.ranges()
        ai.close()
        if faults:
            print(f"crowd-bench: the AI broke an invariant at {n} agents: {'; '.join(faults)}", file=sys.stderr)
            return 1
        # The median step reuses the separation's neighbour list; the mean and p95 include its rebuilds.
        row = {"path": "cpu", "agents": n, "ms_per_step": round(float(np.median(times)) * 1e3, 4), "mean_ms": round(float(np.mean(times)) * 1e3, 4),
               "p95_ms": round(float(np.percentile(times, 95)) * 1e3, 4), "separation_ms": round(float(np.median(spent)) * 1e3, 4),
               "separation_mean_ms": round(float(np.mean(spent)) * 1e3, 4),
               "list_builds_per_step": round((ai.pair_builds - builds) / args.steps, 4), "states": ai.counts(),
               "think_every": think_every, "budgeted": ai.budgeted(), "exact": ai.exact_count(), "workers": used, "town": town}
        rows.append(row)
        print(f"{n:>8} {think_every if ai.budgeted() else 1:>11} {used:>7} {row['ms_per_step']:>9.3f} {row['mean_ms']:>7.3f} {row['p95_ms']:>8.3f} "
              f"{row['separation_ms']:>11.3f} {row['list_builds_per_step']:>12.3f} {row['states']['chase']:>8} {row['exact']:>6}"
              + ("  town" if town else ""))
    return rows




THRESHOLD_M = 1e-3  # an agent this near a radius a transition tests may fall either side of it in float32


def near_threshold(ai, tolerance: float = THRESHOLD_M) -> np.ndarray:
    """Agents of a numpy CrowdAI whose distance to the player is within `tolerance` of a radius one of its
    transitions tests (notice, forget, reach, a blow's reach): where float32 and float64 may disagree."""
    cfg = ai.config
    d = np.hypot(ai.x - ai.player[0], ai.z - ai.player[1])
    grown = cfg.alert(ai.time)
    radii = (cfg.notice_radius + grown, cfg.forget_radius + grown, cfg.attack_reach, cfg.attack_reach * 1.25)
    return np.any([np.abs(d - r) < tolerance for r in radii], axis=0)


def crowd_figures(x, z, vx, vz, state, r: float) -> dict:
    """A crowd's aggregates (all pairs: a few thousand agents): state counts, the living's mean speed,
    overlap depth an agent (separation radius `r`), nearest-neighbour distance percentiles (5, 25, 50 %)."""
    from crowd.sim.config import DYING

    live = state < DYING
    pos = np.stack([x[live], z[live]], 1)
    d = np.sqrt(((pos[:, None] - pos[None]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    overlap = np.maximum(r - d, 0.0)[np.triu_indices(len(pos), 1)]
    return {"counts": np.bincount(state, minlength=6), "speed": float(np.hypot(vx, vz)[live].mean()),
            "overlap": float(overlap.sum() / len(pos)), "nearest": np.percentile(d.min(1), [5, 25, 50])}


def bench_agreement(args) -> int:
    """``crowd-bench ai-agreement``: the GPU AI against its float64 reference, the numpy AI. Per seed, from
    identical state a fight into (the player amid the crowd, blows dealt), one substep on each path: the
    largest difference of each field over every agent (the agents within 1 mm of a radius a transition
    tests left out and counted), and the agents whose state or action differ. Then 600 substeps of a
    crowd round a circling, striking player on each path: the aggregates side by side."""
    import dataclasses

    from crowd.anim.roles import bake_roles, match_roles
    from crowd.asset.gltf import load_character
    from crowd.gl import describe, headless_context
    from crowd.sim.ai import CrowdAI
    from crowd.sim.config import AIConfig
    from crowd.sim.gpu.ai import GpuCrowdAI
    from crowd.sim.motion import motion_for

    character = load_character(args.model)
    roles, _ = match_roles(character.clips)
    motion = motion_for(character, bake_roles(character, roles), roles)
    ctx = headless_context(430)
    info = describe(ctx)
    print(f"{info['gl_renderer']}, {info['gl_version']} | {device_cpu()}")
    config = AIConfig(think_every=1, workers=1, start_clear=0.0)
    fields = ("x", "z", "vx", "vz", "hx", "hz", "phase", "tx", "tz", "state_time", "action_time", "cooldown", "aware", "pause")
    worst = {name: 0.0 for name in fields}
    near_count = differ = agents = 0
    for seed in steps(range(1, args.seeds + 1), desc="one substep", unit="seed"):
        ai = CrowdAI(args.agents, seed, motion, config, origin=(40.0, -25.0))
        ai.player = ai.origin + np.array([2.0, 1.0])
        for k in range(40 + 7 * seed):
            ai.step(1 / 60)
            if k % 10 == 5:
                ai.hit(np.flatnonzero(ai.alive())[::7])
        with GpuCrowdAI(ctx, ai) as g:
            ai.step(1 / 60)
            g.step(1 / 60)
            s = g.download()
        near = near_threshold(ai)
        free = ~near
        near_count += int(near.sum())
        agents += ai.n
        differ += int(np.count_nonzero(((ai.state != s["state"]) | (ai.action != s["action"])) & free))
        for name in fields:
            worst[name] = max(worst[name], float(np.abs(getattr(ai, name) - s[name])[free].max()))
    print(f"one substep, {args.seeds} seeds x {args.agents} agents: state or action differ for {differ} agents "
          f"({near_count} within 1 mm of a radius left out)")
    print("  largest difference: " + ", ".join(f"{k} {v:.2e}" for k, v in worst.items()))
    figures = {}
    for path in ("cpu", "gpu"):
        ai = CrowdAI(args.agents, 5, motion, config)
        g = GpuCrowdAI(ctx, ai) if path == "gpu" else None
        walker = g or ai
        for k in range(600):
            angle = k / 60 * 0.2
            walker.player = ai.origin + 12.0 * np.array([np.cos(angle), np.sin(angle)])
            if k % 54 == 53:
                walker.strike_nearest(walker.player, 2.0)
            walker.step(1 / 60)
        if g is not None:
            g.store(ai)
            g.release()
        got = crowd_figures(ai.x, ai.z, ai.vx, ai.vz, ai.state, config.separation_radius)
        figures[path] = {"states": ai.counts(), "mean_speed": round(got["speed"], 4), "overlap_m_per_agent": round(got["overlap"], 5),
                         "nearest_p5_p25_p50": [round(float(v), 4) for v in got["nearest"]],
                         "outside_world": int(np.count_nonzero((np.abs(ai.x - ai.origin[0]) > ai.half_extent) | (np.abs(ai.z - ai.origin[1]) > ai.half_extent)))}
        print(f"600 substeps, {path}: {figures[path]}")
    ctx.release()
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps({"one_substep": {"largest": worst, "differ": differ, "near_threshold": near_count,
                                                                          "agents": agents}, "600_substeps": figures}, indent=1).encode())
    return 0
