"""``crowd-bench skate``: foot skate (crowd.anim.foot_skate) of the AI's locomotion, per clip at its
natural speed, for the idle/walk/run blends at speeds from 0 to the run speed, and at the two worst
speeds, searched for: below the walk's slowest playback (idle fading in) and from there to the run.

Each case is one agent walking straight at a steady speed for ``--seconds``, animated as the AI
animates it (crowd.sim.locomotion.locomotion_layers: the blend weights from its speed and one phase advanced by
speed over the blended stride). Its feet are measured twice, from the same layers: through the GPU
processor's palette (what is drawn) and through the float64 reference (the clips themselves), so a
slide that the reference shows too is in the clips and the blending, not in the bake.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from crowd.search import golden_section_max


def cases(motion, speeds: int) -> list[tuple[str, float]]:
    """(name, speed): idle, walk and run alone at their natural speeds, then `speeds` blends from 0 to
    the run speed."""
    out = [("idle alone", 0.0), ("walk alone", motion.walk_speed), ("run alone", motion.run_speed)]
    out += [(f"blend {v:.2f} m/s", float(v)) for v in np.linspace(0.0, motion.run_speed, speeds)]
    return out


def _slide(skeleton, clips, feet, names, motion, speed: float, frames: int, dt: float, palette=None):
    """One straight walk at `speed`: its foot skate through `palette(layers, walked, dt)` (the GPU's, or
    a locked one: ``_locked``), or the reference's."""
    from crowd.anim import accuracy
    from crowd.anim.foot_skate import joint_positions, measure, to_world
    from crowd.sim.locomotion import locomotion_layers

    layers, walked = locomotion_layers(motion, speed, frames, dt)
    matrices = accuracy.truth(skeleton, clips, layers) if palette is None else palette(layers, walked, dt)
    ground = np.stack([np.zeros(frames), walked], axis=1)  # straight ahead, along the agent's front (+z)
    return measure(to_world(joint_positions(matrices, skeleton, feet), ground, 0.0), dt, float(walked[-1]), names)


def _locked(bake, legs, processor=None):
    """A palette for ``_slide`` with the foot lock: frame after frame through `processor` (one agent, the
    GPU's lock, reset first), or through the float64 twins of the processor and the lock."""
    from crowd.anim.foot_lock import FootLockTwin
    from crowd.anim.palette_reference import reference_palette

    def palette(layers, walked, dt):
        twin = FootLockTwin(legs, 1)
        if processor is not None:
            processor.reset_lock()
        matrices = []
        for f in range(len(layers)):
            step = walked[f] - walked[f - 1] if f else 0.0
            agent = np.array([[0.0, step, 0.0, 1.0]], np.float32)  # straight ahead along +z, front +z, scale 1
            if processor is None:
                matrices.append(reference_palette(bake, layers[f:f + 1], foot_lock=twin, motion=agent, dt=dt if f else 0.0)[0])
            else:
                processor.process(layers[f:f + 1], agent, dt if f else 0.0)
                matrices.append(processor.read_palette()[0].astype(np.float64))
        return np.array(matrices)

    return palette


def worst_speed(score, low: float, high: float, grid: int = 24, rounds: int = 12) -> float:
    """The speed in [low, high] at which `score(speed)` (the reference's worst foot, cm/m) is largest: a
    grid, then golden-section search in the bracket around the grid's best. The slide is a smooth
    function of speed between the blend's corners, so the grid finds the bump and the search its top."""
    speeds = np.linspace(low, high, grid)
    scores = [score(float(v)) for v in speeds]
    best = int(np.nanargmax(scores))
    a, b = float(speeds[max(best - 1, 0)]), float(speeds[min(best + 1, grid - 1)])
    x, fx = golden_section_max(score, a, b, rounds)
    return x if fx > scores[best] else float(speeds[best])


def measure_cases(ctx, character, bake, motion, speeds: int = 10, seconds: float = 4.0, rate: float = 120.0, search: bool = True) -> list[dict]:
    """Foot skate of every case, on the GPU and on the float64 reference. With `search`, two more
    cases: the worst speed below the walk's slowest playback (where idle fades in) and the worst from
    there to the run speed, each found by search on the reference (``worst_speed``)."""
    from crowd.anim import accuracy
    from crowd.anim.foot_lock import bake_legs
    from crowd.anim.foot_skate import foot_joints
    from crowd.anim.processor import AnimationProcessor
    from crowd.gl import has_compute
    from crowd.progress import steps

    skeleton = character.skeleton
    feet = foot_joints(skeleton)
    if not feet:
        raise SystemExit(f"crowd-bench skate: no joint of {character.name!r} is named like a foot, ankle, toe or ball")
    names = [skeleton.names[j] for j in feet]
    frames, dt = max(2, int(round(seconds * rate))), 1.0 / rate
    clips = [character.clip(c.name) for c in bake.clips]
    chosen = cases(motion, speeds)
    if search:
        score = lambda v: _slide(skeleton, clips, feet, names, motion, v, frames, dt).worst_cm_per_m
        slowest = motion.walk_slowest * motion.walk_speed
        chosen.append(("worst below slowest walk", worst_speed(score, 0.02 * slowest, slowest)))
        chosen.append(("worst walk to run", worst_speed(score, slowest, motion.run_speed)))
    gpu = lambda layers, walked, dt: accuracy.gpu_palette(ctx, bake, layers)
    legs = bake_legs(skeleton, bake)
    locked = None
    if search and len(legs):  # the lock moves the worst speeds: searched again, on the lock's float64 twin
        score = lambda v: _slide(skeleton, clips, feet, names, motion, v, frames, dt, _locked(bake, legs)).worst_cm_per_m
        chosen.append(("worst below slowest, locked", worst_speed(score, 0.02 * slowest, slowest)))
        chosen.append(("worst walk to run, locked", worst_speed(score, slowest, motion.run_speed)))
    if len(legs) and has_compute(ctx):
        locked = AnimationProcessor(ctx, bake, 4, path="compute", legs=legs)
        locked.resize(1)
    rows = []
    try:
        for name, speed in steps(chosen, desc="skate", unit="case"):
            row = {"case": name, "speed_m_s": round(speed, 4), "frames": frames, "dt_s": dt}
            for source, palette in (("gpu", gpu), ("reference", None)):
                row[source] = _slide(skeleton, clips, feet, names, motion, speed, frames, dt, palette).as_dict()
            if locked is not None:  # with the foot lock: the GPU's, and the float64 twin's of the baked keys
                for source, palette in (("gpu_locked", _locked(bake, legs, locked)), ("reference_locked", _locked(bake, legs))):
                    row[source] = _slide(skeleton, clips, feet, names, motion, speed, frames, dt, palette).as_dict()
            rows.append(row)
    finally:
        if locked is not None:
            locked.release()
    return rows


CROWD_CASES = ("walks straight", "walks and turns", "stands or shuffles, straight", "stands or shuffles, turning",
               "blends walk and run, straight", "blends and turns")


def crowd_breakdown(character, bake, motion, agents: int, steps: int = 300, dt: float = 1.0 / 30.0, sample: int = 32,
                    seed: int = 1, foot_lock: bool = False) -> dict:
    """Where a wandering crowd's foot skate comes from, on the float64 reference: `sample` agents of a
    crowd of `agents` stepped `steps` times, their feet over stretches of steady locomotion (wandering or
    chasing) of 1 s or more, each contact frame step's slide filed under what the agent did in it (its
    speed against its walk speed, and whether its heading changed). Figures are cm per metre walked by
    all of them together, so the cases add up to the total. With `foot_lock` the feet are the baked
    keys' through the processor's float64 twin with the lock's twin (crowd.anim.foot_lock) run over
    every step; without, the source clips' (the reference)."""
    from crowd.anim import accuracy
    from crowd.anim.foot_skate import contact_steps, foot_joints, joint_positions, to_world
    from crowd.sim.ai import CrowdAI
    from crowd.sim.config import CHASE, WANDER
    from crowd.sim.motion import upper_body_mask

    skeleton = character.skeleton
    feet = foot_joints(skeleton)
    clips = [character.clip(c.name) for c in bake.clips]
    ai = CrowdAI(agents, seed, motion)
    picked = np.unique(np.linspace(0, agents - 1, min(sample, agents)).astype(np.int64))
    layers, ground, yaw, state, speed = [], [], [], [], []
    for _ in range(steps):
        ai.step(dt)
        layers.append(ai.write_layers()[picked].copy())
        ground.append(np.stack([ai.x[picked], ai.z[picked]], axis=1))
        yaw.append(ai.yaw[picked])
        state.append(ai.state[picked].copy())
        speed.append(np.hypot(ai.vx[picked], ai.vz[picked]) / ai.walk_top[picked])
    layers, ground, yaw, state, speed = map(np.array, (layers, ground, yaw, state, speed))
    locked = None
    if foot_lock:
        from crowd.anim.foot_lock import FootLockTwin, bake_legs
        from crowd.anim.palette_reference import reference_palette

        twin = FootLockTwin(bake_legs(skeleton, bake), picked.size)
        masks = upper_body_mask(skeleton)
        scale = ai.scale[picked].astype(np.float64)
        locked = []
        for f in range(steps):
            step = ground[f] - ground[max(f - 1, 0)]
            lock_motion = np.column_stack([step, np.sin(yaw[f]) * scale, np.cos(yaw[f]) * scale])
            locked.append(reference_palette(bake, layers[f], masks, foot_lock=twin, motion=lock_motion, dt=dt if f else 0.0))
        locked = np.array(locked)
    slide, frames, walked = np.zeros(len(CROWD_CASES)), np.zeros(len(CROWD_CASES), np.int64), 0.0
    min_frames = int(round(1.0 / dt))
    for i in range(picked.size):
        steady = np.flatnonzero(np.isin(state[:, i], (WANDER, CHASE)))
        for run in np.split(steady, np.flatnonzero(np.diff(steady) > 1) + 1):
            if run.size < min_frames:
                continue
            matrices = accuracy.truth(skeleton, clips, layers[run, i]) if locked is None else locked[run, i]
            model = joint_positions(matrices, skeleton, feet)
            world = to_world(model, ground[run, i], yaw[run, i], float(ai.scale[picked[i]]))
            both, moves = contact_steps(world)
            step = np.where(both, moves, 0.0).sum(axis=1)
            turned = np.abs(np.angle(np.exp(1j * np.diff(yaw[run, i])))) > 1e-9
            rel = speed[run[1:], i]
            kind = np.where(rel < motion.walk_slowest, 1, np.where(rel <= 1.0 + 1e-9, 0, 2)) * 2 + turned  # CROWD_CASES' order
            np.add.at(slide, kind, step)
            np.add.at(frames, kind, 1)
            walked += float(np.linalg.norm(np.diff(ground[run, i], axis=0), axis=1).sum())
    per_m = 100.0 * slide / max(walked, 1e-12) / len(feet)
    return {"agents": agents, "foot_lock": foot_lock, "sampled": int(picked.size), "steps": steps, "dt_s": dt, "walked_m": round(walked, 3),
            "total_cm_per_m": round(float(per_m.sum()), 4),
            "cases": {name: {"cm_per_m": round(float(v), 4), "frames": int(f)} for name, v, f in zip(CROWD_CASES, per_m, frames)}}


def run(args) -> int:
    from crowd.anim.roles import bake_roles, match_roles
    from crowd.asset.gltf import load_character
    from crowd.gl import describe, headless_context
    from crowd.sim.motion import motion_for
    from crowd.anim.foot_skate import CONTACT_M, SKATE_SPEED_M_S

    from .common import device_cpu

    character = load_character(args.model)
    roles, _ = match_roles(character.clips)
    bake = bake_roles(character, roles)
    motion = motion_for(character, bake, roles)
    if args.crowd:
        reports = [crowd_breakdown(character, bake, motion, args.crowd, foot_lock=lock) for lock in (False, True)]
        report = reports[0]
        print(f"{character.name} | a crowd of {args.crowd}: {report['sampled']} agents sampled, {report['steps']} steps of "
              f"{report['dt_s']:.4f} s, {report['walked_m']:.1f} m walked in steady stretches of 1 s or more (float64 reference; "
              f"with the lock, the baked keys through the processor's and the lock's float64 twins)")
        print(f"{'frames where the agent':>32} {'cm/m':>8} {'locked':>8} {'frames':>8}")
        for name, case in report["cases"].items():
            print(f"{name:>32} {case['cm_per_m']:>8.3f} {reports[1]['cases'][name]['cm_per_m']:>8.3f} {case['frames']:>8}")
        print(f"{'total':>32} {report['total_cm_per_m']:>8.3f} {reports[1]['total_cm_per_m']:>8.3f}")
        if args.json:
            from crowd.files import atomic_write_bytes

            atomic_write_bytes(Path(args.json), json.dumps({"without_lock": reports[0], "with_lock": reports[1]}, indent=1).encode())
        return 0
    ctx = headless_context()
    info = describe(ctx)
    rows = measure_cases(ctx, character, bake, motion, args.speeds, args.seconds, args.rate, not args.no_search)
    print(f"{info['gl_renderer']} | {character.name} | contact: within {CONTACT_M * 100:.0f} cm of the joint's lowest point; "
          f"skating: faster than {SKATE_SPEED_M_S * 100:.0f} cm/s | {args.seconds} s at {args.rate:.0f} Hz a case")
    print(f"{'case':>25} {'m/s':>6} {'GPU cm/m':>9} {'worst':>7} {'cm/s':>6} {'over':>6} {'ref cm/m':>9} {'worst':>7} {'contact':>8}"
          f" | {'locked GPU':>10} {'worst':>7} {'over':>6} {'twin':>7}")
    for r in rows:
        g, t = r["gpu"], r["reference"]
        lock = ""
        if "gpu_locked" in r:
            gl, tl = r["gpu_locked"], r["reference_locked"]
            lock = f" | {gl['slide_cm_per_m']:>10.3f} {gl['worst_cm_per_m']:>7.3f} {gl['share_over']:>6.1%} {tl['slide_cm_per_m']:>7.3f}"
        print(f"{r['case']:>25} {r['speed_m_s']:>6.2f} {g['slide_cm_per_m']:>9.3f} {g['worst_cm_per_m']:>7.3f} {g['slide_cm_per_s']:>6.2f} "
              f"{g['share_over']:>6.1%} {t['slide_cm_per_m']:>9.3f} {t['worst_cm_per_m']:>7.3f} {g['contact_share']:>8.1%}{lock}")
    if args.json:
        from crowd.files import atomic_write_bytes

        report = {"device": f"{info['gl_renderer']}; {device_cpu()}", "model": character.name, "contact_m": CONTACT_M,
                  "skate_speed_m_s": SKATE_SPEED_M_S, "rows": rows}
        atomic_write_bytes(Path(args.json), json.dumps(report, indent=1).encode())
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("skate", help="foot skate of the AI's locomotion: per clip and for blends at 0 to the run speed")
    p.add_argument("--model", type=Path, help="a .glb/.gltf (default: the built-in zombie)")
    p.add_argument("--speeds", type=int, default=10, help="blend speeds from 0 to the run speed")
    p.add_argument("--seconds", type=float, default=4.0, help="seconds walked a case")
    p.add_argument("--rate", type=float, default=120.0, help="frames a second measured")
    p.add_argument("--crowd", type=int, default=0, metavar="AGENTS",
                   help="instead: where a wandering crowd of AGENTS zombies slides, by what each agent was doing (CPU only)")
    p.add_argument("--no-search", action="store_true", help="leave out the searched worst speeds (two extra cases)")
    p.add_argument("--json", type=Path, help="write the rows here as JSON (atomically)")
    p.set_defaults(run=run)
