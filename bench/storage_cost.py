"""``crowd-bench storage-cost``: the animation processor's GPU ms for each storage (f32, f16, compressed at a
bound) and interpolation, on both processor paths, side by side in one run.

``crowd-bench error`` times only the path "auto" takes, once per configuration it also searches for errors;
this times every (storage, interpolation, path) in passes that alternate them (forward, backward, forward),
so drift on the machine shows as spread, for 4-layer random blends of the built-in zombie's clips. Medians of
the passes are reported, with the bytes of animation data each storage puts on the GPU. With ``--foot-lock``
the compute path is timed again with the foot lock (crowd.anim.foot_lock), each agent stepping 1 cm a run
in a direction of its own, so its legs are held, solved and stepped as a walking crowd's are.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

PASSES = 3


def run(args) -> int:
    from crowd.anim import accuracy
    from crowd.anim.foot_lock import bake_legs
    from crowd.anim.processor import AnimationProcessor
    from crowd.asset.gltf import load_character
    from crowd.frame import MAX_LAYERS
    from crowd.gl import describe, has_compute, headless_context
    from crowd.settings import SETTINGS
    from crowd.progress import steps
    from .error_report import UNTIMED_MS, _time_processor
    from .stability import bake_storage, parse_storage

    storages = args.storage.split(",")
    interpolations = args.interpolations.split(",")
    agents = [int(a) for a in args.agents.split(",")]
    try:
        for s in storages:
            parse_storage(s)
        for i in interpolations:
            SETTINGS["interpolation"].check(i)
    except ValueError as exc:
        raise SystemExit(f"crowd-bench storage-cost: {exc}") from None
    ctx = headless_context()
    info = describe(ctx)
    paths = ["compute", "fragment"] if has_compute(ctx) else ["fragment"]
    zombie = load_character(None)
    bakes = {s: bake_storage(zombie.skeleton, list(zombie.clips), args.fps, s) for s in storages}
    layers = [accuracy.draw_samples(zombie.clips, np.random.default_rng(args.seed), 0, n).layers for n in agents]
    rng = np.random.default_rng(args.seed)
    motion = []
    for n in agents:
        heading = rng.uniform(0.0, 2.0 * np.pi, n)
        motion.append(np.column_stack([0.01 * np.sin(heading), 0.01 * np.cos(heading), np.sin(heading), np.cos(heading)]).astype(np.float32))
    query = ctx.query(time=True)
    locks = (False, True) if args.foot_lock else (False,)
    legs = {s: bake_legs(zombie.skeleton, bakes[s]) for s in storages} if args.foot_lock else {}
    keys = [(s, i, p, lock) for s in storages for i in interpolations for p in paths for lock in locks if not (lock and p != "compute")]
    times: dict = {k: [] for k in keys}
    runs = [k for order in (keys, keys[::-1], keys) for k in order]  # PASSES of them, alternated
    for s, i, p, lock in steps(runs, desc="storage-cost", unit="run"):
        proc = AnimationProcessor(ctx, bakes[s], MAX_LAYERS, interpolation=i, path=p,
                                  legs=legs[s] if lock else None)
        try:
            times[(s, i, p, lock)].append([_time_processor(query, proc, l, args.repeats, m, 1.0 / 60.0) for l, m in zip(layers, motion)])
        finally:
            proc.release()
    measured = any(v > UNTIMED_MS for t in times.values() for pair in t for v in pair)
    print(f"{info['gl_renderer']} | {info['gl_version']} | {args.fps:g} fps bakes, {MAX_LAYERS}-layer blends, {PASSES} passes alternated")
    rows = []
    for (s, i, p, lock), t in times.items():
        t = np.array(t)  # (passes, sizes)
        median = np.median(t, axis=0)
        row = {"storage": s, "interpolation": i, "path": p, "foot_lock": lock, "bytes": bakes[s].nbytes,
               "gpu_ms": {str(n): (float(m) if measured else None) for n, m in zip(agents, median)},
               "spread": (float((t[:, -1].max() - t[:, -1].min()) / median[-1]) if measured and median[-1] > 0 else None)}
        rows.append(row)
        cells = "  ".join(f"{n:,}: {m:.4f} ms" for n, m in zip(agents, median)) if measured else "GPU ms not measured here"
        spread = f"  spread {row['spread']:.1%}" if row["spread"] is not None else ""
        print(f"{s:>16} {i:<12} {p + (' +lock' if lock else ''):<14} {bakes[s].nbytes:>9,} B  {cells}{spread}")
    if not measured:
        print(f"GPU ms not measured here: {info['gl_renderer']}'s timer queries answer 0 or 1 ns")
    if args.json:
        from crowd.files import atomic_write_bytes

        report = {"gl": info, "fps": args.fps, "agents": agents, "repeats": args.repeats, "passes": PASSES, "gpu_ms_measured": measured,
                  "rows": rows}
        atomic_write_bytes(Path(args.json), json.dumps(report, indent=1).encode())
    ctx.release()
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("storage-cost", help="processor GPU ms of each storage and interpolation on both paths, alternated in one run")
    p.add_argument("--storage", default="f32,f16,compressed@0.5,compressed@0.1",
                   help='storages: f32, f16, or compressed at a bound in mm ("compressed@0.5")')
    p.add_argument("--interpolations", default="qt_lerp,qt_corrected", help='comma-separated interpolations to time')
    p.add_argument("--agents", default="10000,100000", help="crowd sizes timed")
    p.add_argument("--fps", type=float, default=30.0, help="bake rate")
    p.add_argument("--repeats", type=int, default=30, help="timed runs per size and pass")
    p.add_argument("--seed", type=int, default=8, help="random seed of the blends and the agents' motion")
    p.add_argument("--foot-lock", action="store_true", help="also time the compute path with the foot lock")
    p.add_argument("--json", type=Path, help='write the results as JSON to this file')
    p.set_defaults(run=run)
