"""``crowd-demo``: the demo entry point. Thin: it parses flags and calls the stages.

The interactive window comes with issue 6. Until then, and on any machine without a display, the demo
runs the headless smoke mode: the whole frame loop offscreen through EGL, a PNG of the last frame and
a JSON of stats.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="crowd-demo", description="Zombie crowd demo: GPU animation processor and skinned instancing.")
    p.add_argument("--headless", action="store_true", help="run offscreen through EGL even when a display exists")
    p.add_argument("--frames", type=int, default=60, help="frames to run (default 60)")
    p.add_argument("--agents", type=int, default=200, help="number of zombies (default 200)")
    p.add_argument("--size", default="1280x720", help="frame size WxH (default 1280x720)")
    p.add_argument("--screenshot", type=Path, default=Path("out/demo.png"), help="PNG of the last frame")
    p.add_argument("--stats", type=Path, default=None, help="JSON of frame and pass timings")
    p.add_argument("--model", type=Path, default=None, help="a skinned .glb/.gltf (default: the built-in zombie)")
    p.add_argument("--roles", default=None, help="clip role overrides, e.g. walk=Walking,idle=Idle")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--bake-fps", type=float, default=15.0)
    p.add_argument("--precision", choices=["f32", "f16"], default="f32")
    p.add_argument("--processor", choices=["auto", "compute", "fragment"], default="auto", help="processor path (default: compute where GL 4.3 exists)")
    p.add_argument("--no-shadows", action="store_true")
    p.add_argument("--no-culling", action="store_true")
    p.add_argument("--no-weapons", action="store_true", help="nobody is armed: no socket read-back, no gather pass")
    p.add_argument("--readback-latency", type=int, default=2, help="frames between gathering a weapon socket and reading it (1-3)")
    return p


def main(argv=None) -> int:
    args = _parser().parse_args(argv)

    from crowd.ai import AIError
    from crowd.bake import BakeError
    from crowd.gl import GLUnavailable, has_display
    from crowd.gltf import GltfImportError
    from crowd.pipeline import MAX_AGENTS, PipelineConfig, PipelineError, smoke_size
    from crowd.processor import ProcessorError
    from crowd.readback import ReadbackError
    from crowd.render import RenderError
    from crowd.roles import RoleError, parse_overrides
    from crowd.smoke import run_headless
    from crowd.weapons import WeaponError

    if not args.headless:
        reason = "no display found" if not has_display() else "the interactive window is not built yet (issue 6)"
        print(f"crowd-demo: {reason}; running headless (EGL) instead.")
    try:
        if not 1 <= args.frames <= 100_000:
            raise PipelineError(f"--frames must be 1 to 100000, got {args.frames}")
        if not 0 <= args.agents <= MAX_AGENTS:
            raise PipelineError(f"--agents must be 0 to {MAX_AGENTS}, got {args.agents}")
        if args.model is not None and not args.model.is_file():
            raise PipelineError(f"--model {args.model}: no such file")
        config = PipelineConfig(agents=args.agents, seed=args.seed, model=args.model, roles=parse_overrides(args.roles),
                                bake_fps=args.bake_fps, precision=args.precision, processor_path=args.processor,
                                shadows=not args.no_shadows, culling=not args.no_culling, weapons=not args.no_weapons,
                                readback_latency=args.readback_latency)
        stats = run_headless(config, args.frames, smoke_size(args.size), args.screenshot, args.stats)
    except (AIError, GltfImportError, BakeError, PipelineError, ProcessorError, RenderError, RoleError, GLUnavailable,
            ReadbackError, WeaponError) as exc:
        print(f"crowd-demo: {exc}", file=sys.stderr)
        return 2
    for note in stats["warnings"]:
        print(f"  note: {note}")
    f = stats["frame_ms"]
    print(f"{stats['agents']} agents, {stats['frames']} frames at {stats['size'][0]}x{stats['size'][1]} on {stats['gl_renderer']}: "
          f"frame p50 {f['p50']} ms, p95 {f['p95']} ms; processor ({stats['processor_path']}) {stats['passes_ms'].get('process', 0)} ms; "
          f"{stats['last_frame']['triangles']:,} triangles; NaN rows {stats['nan_count']}")
    w = stats["weapons"]
    if w["enabled"]:
        print(f"weapons: {w['drawn']} drawn, read back {w['latency_frames']} frames late (pose lag {w['pose_lag_ms']} ms); "
              f"weapon-to-hand error {stats['weapon_error_mm']} mm; read-back wait median {stats['readback_wait_ms']['median']} ms, "
              f"max {stats['readback_wait_ms']['max']} ms, {w['stalls']} stalls")
    print(f"wrote {args.screenshot}" + (f" and {args.stats}" if args.stats else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
