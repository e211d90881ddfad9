"""``crowd-bench rounds``: how long a survivor's first round lasts, played without GL by the game's own
rules (crowd.sim.rounds) over several seeds, for two players side by side: the headless script (it
walks a circle and swings on a beat, as the headless demo plays) and one that stands still and never
swings. CPU only: the picture plays no part in the rules."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

PLAYERS = ("scripted", "still")


def _cast(scene):
    """The scene's crowd and survivor, baked (no morph tracks: they play no part in the rules)."""
    from crowd.cast import bake_member, character_motion, load_cast, player_motion

    config = scene.pipeline_config()
    specs = config.cast()
    cast = load_cast(specs, True)
    for k in range(len(cast)):
        cast[k].bake = bake_member(cast, k, config.seed, config.bake_fps, config.precision, config.compression_bound_mm, False)
    for k in range(len(specs)):
        cast[k].motion = character_motion(cast, k)
    return config, specs, cast, player_motion(cast[-1])


def first_round(scene, seed: int, seconds: float, player: str, dt: float = 1 / 30, prepared=None) -> dict:
    """The first round of `scene`'s game at `seed`, for `player` ("scripted" or "still"), up to `seconds`
    simulated: its record (crowd.sim.player.Survivor.round_record) and the crowd's state counts at its end."""
    from crowd.asset.town import build_town
    from crowd.sim.ai import CrowdAI, PlayerScript
    from crowd.sim.player import Survivor
    from crowd.sim.rounds import move_survivor, settle

    config, specs, cast, motion = prepared or _cast(scene)
    obstacles = build_town().obstacles() if config.town else None
    ai = CrowdAI(config.agents, seed, [m.motion for m in cast[:len(specs)]], config.ai, config.origin,
                 shares=[s.share for s in specs], obstacles=obstacles)
    try:
        survivor = Survivor(motion, ai.origin)
        ai.player = survivor.position.copy()
        script = None
        if player == "scripted":  # the pipeline's headless player, on the same circle
            script = PlayerScript.headless(ai)
        seen = 0
        while not survivor.down and survivor.round_time < seconds:
            if script is not None:
                script.update(ai, survivor)
            landed = move_survivor(ai, survivor, dt, obstacles)
            ai.step(dt)
            seen = settle(ai, survivor, landed, seen)
        return {**survivor.round_record(), "states": ai.counts()}
    finally:
        ai.close()


def run(args) -> int:
    from crowd.scene import Scene, load_scene

    scene = load_scene(args.scene) if args.scene else Scene()
    scene = scene.with_overrides(agents=args.agents) if args.agents is not None else scene
    if args.ai:  # settings of the [ai] table, as a scene file or the demo's flags would give them
        from crowd.settings import SETTINGS

        pairs = [item.split("=", 1) for item in args.ai.split(",")]
        scene = scene.with_overrides(**{name.strip(): SETTINGS[name.strip()].from_text(value.strip()) for name, value in pairs})
    seeds = list(range(1, args.seeds + 1))
    prepared = _cast(scene)
    rows = []
    for player in PLAYERS:
        for seed in seeds:
            rows.append({"player": player, "seed": seed, **first_round(scene, seed, args.seconds, player, prepared=prepared)})
    print(f"{scene.agents} agents, town {'on' if scene.town else 'off'}; first round, up to {args.seconds:g} s simulated")
    print(f"{'player':>9} {'median s':>9} {'min s':>7} {'max s':>7} {'still playing':>14} {'kills (median)':>15}")
    summary = {}
    for player in PLAYERS:
        mine = [r for r in rows if r["player"] == player]
        lengths = np.array([r["length_s"] for r in mine])
        playing = sum(r["end"] == "playing" for r in mine)
        summary[player] = {"median_s": float(np.median(lengths)), "min_s": float(lengths.min()), "max_s": float(lengths.max()),
                           "still_playing": playing, "seeds": len(mine), "kills_median": float(np.median([r["kills"] for r in mine]))}
        s = summary[player]
        print(f"{player:>9} {s['median_s']:>9.1f} {s['min_s']:>7.1f} {s['max_s']:>7.1f} {playing:>7} of {len(mine):<4} {s['kills_median']:>15.0f}")
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps({"agents": scene.agents, "town": scene.town, "seconds": args.seconds,
                                                        "rows": rows, "summary": summary}, indent=1).encode())
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("rounds", help="the survivor's first round over seeds, scripted and standing still (CPU, no GL)")
    p.add_argument("--scene", type=Path, help="a scene file (default: the default scene)")
    p.add_argument("--agents", type=int, default=None, help="zombies (default: the scene's)")
    p.add_argument("--seeds", type=int, default=10, help="seeds 1 to N")
    p.add_argument("--ai", default="", metavar="NAME=VALUE,...", help="AI settings for this run, e.g. start_clear=0,alert_rate=0")
    p.add_argument("--seconds", type=float, default=120.0, help="simulated seconds a round may last here")
    p.add_argument("--json", type=Path, help="write the rows and the summary here")
    p.set_defaults(run=run)
