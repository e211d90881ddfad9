"""``crowd-bench skate``: foot skate (crowd.anim.foot_skate) of the AI's locomotion, per clip at its
natural speed and for the idle/walk/run blends at speeds from 0 to the run speed.

Each case is one agent walking straight at a steady speed for ``--seconds``, animated as the AI
animates it (crowd.sim.ai.locomotion_layers: the blend weights from its speed and one phase advanced by
speed over the blended stride). Its feet are measured twice, from the same layers: through the GPU
processor's palette (what is drawn) and through the float64 reference (the clips themselves), so a
slide that the reference shows too is in the clips and the blending, not in the bake.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def cases(motion, speeds: int) -> list[tuple[str, float]]:
    """(name, speed): idle, walk and run alone at their natural speeds, then `speeds` blends from 0 to
    the run speed."""
    out = [("idle alone", 0.0), ("walk alone", motion.walk_speed), ("run alone", motion.run_speed)]
    out += [(f"blend {v:.2f} m/s", float(v)) for v in np.linspace(0.0, motion.run_speed, speeds)]
    return out


def measure_cases(ctx, character, bake, motion, speeds: int = 10, seconds: float = 4.0, rate: float = 120.0) -> list[dict]:
    """Foot skate of every case, on the GPU and on the float64 reference."""
    from crowd.anim import accuracy
    from crowd.anim.foot_skate import foot_joints, joint_positions, measure, to_world
    from crowd.sim.ai import LAYERS, locomotion_layers

    skeleton = character.skeleton
    feet = foot_joints(skeleton)
    if not feet:
        raise SystemExit(f"crowd-bench skate: no joint of {character.name!r} is named like a foot, ankle, toe or ball")
    names = [skeleton.names[j] for j in feet]
    frames, dt = max(2, int(round(seconds * rate))), 1.0 / rate
    runs = [(name, v, *locomotion_layers(motion, v, frames, dt)) for name, v in cases(motion, speeds)]
    layers = np.concatenate([r[2] for r in runs])
    clips = [character.clip(c.name) for c in bake.clips]
    palette = accuracy.gpu_palette(ctx, bake, layers)
    truth = accuracy.truth(skeleton, clips, layers)
    rows = []
    for k, (name, speed, _, walked) in enumerate(runs):
        part = slice(k * frames, (k + 1) * frames)
        ground = np.stack([np.zeros(frames), walked], axis=1)  # straight ahead, along the agent's front (+z)
        row = {"case": name, "speed_m_s": round(speed, 4), "frames": frames, "dt_s": dt}
        for source, matrices in (("gpu", palette[part]), ("reference", truth[part])):
            world = to_world(joint_positions(matrices, skeleton, feet), ground, 0.0)
            row[source] = measure(world, dt, float(walked[-1]), names).as_dict()
        rows.append(row)
    return rows


def run(args) -> int:
    from crowd.anim.roles import bake_roles, match_roles
    from crowd.asset.gltf import load_character
    from crowd.gl import describe, headless_context
    from crowd.sim.ai import motion_for
    from crowd.anim.foot_skate import CONTACT_M, SKATE_SPEED_M_S

    from .common import device_cpu

    character = load_character(args.model)
    roles, _ = match_roles(character.clips)
    bake = bake_roles(character, roles)
    motion = motion_for(character, bake, roles)
    ctx = headless_context()
    info = describe(ctx)
    rows = measure_cases(ctx, character, bake, motion, args.speeds, args.seconds, args.rate)
    print(f"{info['gl_renderer']} | {character.name} | contact: within {CONTACT_M * 100:.0f} cm of the joint's lowest point; "
          f"skating: faster than {SKATE_SPEED_M_S * 100:.0f} cm/s | {args.seconds} s at {args.rate:.0f} Hz a case")
    print(f"{'case':>18} {'m/s':>6} {'GPU cm/m':>9} {'worst':>7} {'cm/s':>6} {'over':>6} {'ref cm/m':>9} {'worst':>7} {'contact':>8}")
    for r in rows:
        g, t = r["gpu"], r["reference"]
        print(f"{r['case']:>18} {r['speed_m_s']:>6.2f} {g['slide_cm_per_m']:>9.3f} {g['worst_cm_per_m']:>7.3f} {g['slide_cm_per_s']:>6.2f} "
              f"{g['share_over']:>6.1%} {t['slide_cm_per_m']:>9.3f} {t['worst_cm_per_m']:>7.3f} {g['contact_share']:>8.1%}")
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
    p.add_argument("--json", type=Path)
    p.set_defaults(run=run)
