"""``crowd-demo``: the demo entry point. Thin: it parses flags and calls the stages.

With a display it opens the window (app/window.py: the crowd, the player marker and the ImGui panel)
and runs until it is closed, or for --frames frames. Without one, or with --headless, it runs the
headless smoke mode: the whole frame loop offscreen through EGL, a PNG of the last frame and a JSON of
stats. The same flags drive both.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _rate(text: str):
    """--bake-fps: a number, or "source" (each clip at its own key rate); the scene checks the range."""
    if text == "source":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected a number of fps or "source", got {text!r}') from None


def _parser() -> argparse.ArgumentParser:
    from crowd.processor import INTERPOLATIONS

    p = argparse.ArgumentParser(prog="crowd-demo", description="Zombie crowd demo: GPU animation processor and skinned instancing.")
    p.add_argument("--headless", action="store_true", help="run offscreen through EGL even when a display exists")
    p.add_argument("--frames", type=int, default=None, help="frames to run (headless default 60; the window runs until closed)")
    p.add_argument("--scene", type=Path, default=None, help="a scene file (TOML; see scenes/); flags given as well override it")
    p.add_argument("--agents", type=int, default=None, help="number of zombies (default: the scene's, 200)")
    p.add_argument("--size", default="1280x720", help="frame size WxH (default 1280x720)")
    p.add_argument("--screenshot", type=Path, default=None, help="PNG of the last frame (headless default out/demo.png)")
    p.add_argument("--stats", type=Path, default=None, help="JSON of frame and pass timings")
    p.add_argument("--model", type=Path, default=None, help="a skinned .glb/.gltf (default: the built-in zombie)")
    p.add_argument("--roles", default=None, help="clip role overrides, e.g. walk=Walking,idle=Idle")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--bake-fps", type=_rate, default=None, help='bake rate, 1-240 or "source" (default: the scene\'s, 30)')
    p.add_argument("--interpolation", choices=list(INTERPOLATIONS), default=None,
                   help="how keys are sampled and layers blended (default: the scene's, qt_lerp; see docs/BENCHMARKS.md)")
    p.add_argument("--precision", choices=["f32", "f16"], default=None)
    p.add_argument("--processor", choices=["auto", "compute", "fragment"], default=None, help="processor path (default: compute where GL 4.3 exists)")
    p.add_argument("--no-shadows", action="store_true")
    p.add_argument("--no-culling", action="store_true")
    p.add_argument("--no-weapons", action="store_true", help="nobody is armed: no socket read-back, no gather pass")
    p.add_argument("--readback-latency", type=int, default=None, help="frames between gathering a weapon socket and reading it (1-3, default 2)")
    return p


def main(argv=None) -> int:
    args = _parser().parse_args(argv)

    from crowd.ai import AIError
    from crowd.bake import BakeError
    from crowd.gl import GLUnavailable, has_display
    from crowd.gltf import GltfImportError
    from crowd.pipeline import PipelineError, smoke_size
    from crowd.processor import ProcessorError
    from crowd.readback import ReadbackError
    from crowd.render import RenderError
    from crowd.roles import RoleError, parse_overrides
    from crowd.scene import Scene, SceneError, load_scene
    from crowd.smoke import run_headless
    from crowd.weapons import WeaponError

    windowed = not args.headless and has_display()
    if not args.headless and not windowed:
        print("crowd-demo: no display found; running headless (EGL) instead.")
    if not windowed:
        _headless_defaults(args)
    try:
        if args.frames is not None and not 1 <= args.frames <= 100_000:
            raise PipelineError(f"--frames must be 1 to 100000, got {args.frames}")
        if args.model is not None and not args.model.is_file():
            raise PipelineError(f"--model {args.model}: no such file")
        scene = Scene()
        if args.scene is not None:
            try:
                scene = load_scene(args.scene)
            except SceneError as exc:  # a broken scene file loses nothing: the run goes on with the defaults
                print(f"crowd-demo: {exc}; running the default scene instead", file=sys.stderr)
        off = lambda flag: False if flag else None  # a --no-x flag turns x off; without it the scene decides
        scene = scene.with_overrides(agents=args.agents, seed=args.seed, model=args.model, roles=parse_overrides(args.roles) or None,
                                     bake_fps=args.bake_fps, precision=args.precision, interpolation=args.interpolation,
                                     processor=args.processor,
                                     shadows=off(args.no_shadows), culling=off(args.no_culling), weapons=off(args.no_weapons),
                                     readback_latency=args.readback_latency)
        size = smoke_size(args.size)
        stats = None
        if windowed:
            stats = _run_window(scene, size, args)
            if stats is None:
                _headless_defaults(args)
        if stats is None:
            stats = run_headless(scene.pipeline_config(), args.frames, size, args.screenshot, args.stats,
                                 camera=scene.camera_for(size[0] / size[1]))
    except (AIError, GltfImportError, BakeError, PipelineError, ProcessorError, RenderError, RoleError, GLUnavailable,
            ReadbackError, WeaponError, SceneError) as exc:
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
    if args.screenshot or args.stats:
        print("wrote " + " and ".join(str(p) for p in (args.screenshot, args.stats) if p))
    return 0


def _headless_defaults(args) -> None:
    """Headless runs stop by themselves and leave a picture: 60 frames and out/demo.png unless given."""
    args.frames = 60 if args.frames is None else args.frames
    args.screenshot = args.screenshot or Path("out/demo.png")


def _run_window(scene, size, args):
    """The window, or None (after one line saying why) when no window can be made here."""
    try:
        from app.window import run_window
    except Exception as exc:  # pyglet raises several types when it finds no usable display
        print(f"crowd-demo: cannot open a window ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}); "
              "running headless (EGL) instead.", file=sys.stderr)
        return None
    try:
        return run_window(scene, size, args.frames, args.screenshot, args.stats, args.scene)
    except Exception as exc:
        if "window" in type(exc).__module__.lower() or "pyglet" in type(exc).__module__.lower() or "Display" in type(exc).__name__:
            print(f"crowd-demo: cannot open a window ({type(exc).__name__}); running headless (EGL) instead.", file=sys.stderr)
            return None
        raise


if __name__ == "__main__":
    raise SystemExit(main())
