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


def _parser() -> argparse.ArgumentParser:
    """The flags: a few of the demo's own, then one per setting of crowd.settings (bounds, defaults and
    help come from there, so the command line, scene files and panel agree)."""
    from crowd.settings import SETTINGS, group

    # allow_abbrev off: with the schema's many flags a prefix such as --se or --re matched several.
    p = argparse.ArgumentParser(prog="crowd-demo", description="Zombie crowd demo: GPU animation processor and skinned instancing.",
                                allow_abbrev=False)
    p.add_argument("--headless", action="store_true", help="run offscreen through EGL even when a display exists")
    p.add_argument("--scene", type=Path, default=None, help="a scene file (TOML; see scenes/); flags given as well override it")
    p.add_argument("--screenshot", type=Path, default=None, help="PNG of the last frame (headless default out/demo.png)")
    p.add_argument("--stats", type=Path, default=None, help="JSON of frame and pass timings")
    p.add_argument("--clip", type=Path, default=None, help="headless: the run's last 90 frames (3 s) as an animated .webp or "
                                                           ".gif (each frame is read back, so timings include that)")
    p.add_argument("--panel", action="store_true", help="headless: draw the frame as the window does: the panel, the HUD and "
                                                        "the camera behind the survivor (the window always does)")
    p.add_argument("--model", default=None, help="one character for the whole crowd: a skinned .glb/.gltf, or a built-in's name "
                                                 "(zombie, brute); default: the scene's cast")
    p.add_argument("--characters", default=None, metavar="MODEL=SHARE,...",
                   help="a mixed crowd: models (built-in names or files) and their relative shares, e.g. zombie=3,brute=1,x.glb=1")
    p.add_argument("--roles", default=None, help="clip role overrides of a crowd of one character, e.g. walk=Walking,idle=Idle")
    p.add_argument("--clips", nargs="+", default=None, metavar="FILE",
                   help="glTF files whose clips join the character's (an animation library, Mixamo's animations), matched to its "
                        "joints by name; a crowd of one character")
    for name in ("frames", "size", "view"):
        s = SETTINGS[name]
        p.add_argument(s.flag, default=None, metavar=s.name.upper(), help=f"{s.help} ({s.rule()})")
    titles = {"scene": "crowd", "clips": "the bake", "features": "what is drawn", "ai": "the crowd's behaviour (scene table [ai])"}
    for table, title in titles.items():
        g = p.add_argument_group(title)
        for s in group(table).values():
            if s.kind == "bool" and s.default:  # a switch on by default: the flag turns it off for this run
                g.add_argument("--no-" + s.flag[2:], dest=s.name, action="store_const", const="false", default=None, help=f"no {s.help}")
            elif s.kind == "bool":  # off by default (occlusion culling): the flag turns it on
                g.add_argument(s.flag, dest=s.name, action="store_const", const="true", default=None, help=s.help)
            else:
                g.add_argument(s.flag, dest=s.name, default=None, metavar=_metavar(s),
                               help=f"{s.help} ({s.rule()}; default: the scene's, {_show(s.default)})")
    return p


def _metavar(setting) -> str:
    if setting.kind == "ascending":
        return ",".join(f"D{k + 1}" for k in range(len(setting.default)))
    return {"choice": "{" + ",".join(setting.choices) + "}", "rate": "FPS", "int": "N"}.get(setting.kind, "X")


def _show(value) -> str:
    return ",".join(f"{v:g}" for v in value) if isinstance(value, tuple) else (f"{value:g}" if isinstance(value, float) else str(value))


def main(argv=None) -> int:
    args = _parser().parse_args(argv)

    from crowd.errors import CrowdError
    from crowd.gl import has_display
    from crowd.asset.gltf import BUILT_IN, is_built_in
    from crowd.anim.roles import parse_overrides
    from crowd.scene import Scene, SceneError, load_scene
    from crowd.settings import SETTINGS, SCENE_GROUPS, group, parse
    from crowd.pipeline_config import PipelineError
    from crowd.smoke import run_headless

    windowed = not args.headless and has_display()
    if not args.headless and not windowed:
        print("crowd-demo: no display found; running headless (EGL) instead.")
    if not windowed:
        _headless_defaults(args)
    try:
        args.frames = None if args.frames is None else parse("frames", str(args.frames), SceneError, "--frames")
        if args.model is not None and not is_built_in(args.model) and not Path(args.model).is_file():
            raise PipelineError(f"--model {args.model}: no such file (nor a built-in: {', '.join(BUILT_IN)})")
        characters = None if args.characters is None else _cast_flag(args.characters)
        for file in args.clips or ():
            if not Path(file).is_file():
                raise PipelineError(f"--clips {file}: no such file")
        scene = Scene()
        if args.scene is not None:
            try:
                scene = load_scene(args.scene)
            except SceneError as exc:  # a broken scene file loses nothing: the run goes on with the defaults
                print(f"crowd-demo: {exc}; running the default scene instead", file=sys.stderr)
        # Every setting flag given, its text as the setting's type; the scene checks it, naming the flag.
        given = {name: SETTINGS[name].from_text(text) for table in SCENE_GROUPS
                 for name in group(table) if (text := getattr(args, name)) is not None}
        scene = scene.with_overrides(model=args.model, characters=characters, roles=parse_overrides(args.roles) or None, files=args.clips,
                                     **given)
        size = SETTINGS["size"].default if args.size is None else parse("size", args.size, SceneError, "--size")
        stats = None
        if windowed:
            stats = _run_window(scene, size, args)
            if stats is None:
                _headless_defaults(args)
        if stats is None:
            overlay = None
            if args.panel:
                from app.overlay import HeadlessPanel

                overlay = HeadlessPanel.factory(scene, follow=True)
            view = SETTINGS["view"].default if args.view is None else parse("view", args.view, SceneError, "--view")
            if args.clip is not None and args.clip.suffix.lower() not in (".webp", ".gif"):
                raise SceneError(f"--clip {args.clip}: a clip is written as .webp or .gif")
            stats = run_headless(scene.pipeline_config(), args.frames, size, args.screenshot, args.stats,
                                 camera=scene.camera_for(size[0] / size[1]) or view, overlay=overlay, clip=args.clip)
    except CrowdError as exc:
        print(f"crowd-demo: {exc}", file=sys.stderr)
        return 2
    for note in stats["warnings"]:
        print(f"  note: {note}")
    period, latency = stats["frame_period_ms"], stats["frame_latency_ms"]
    paced = f"frame period p50 {period['p50']} ms, p95 {period['p95']} ms; " if period else ""
    timed = f"latency p50 {latency['p50']} ms, p95 {latency['p95']} ms; " if latency else ""
    print(f"{stats['agents']} agents, {stats['frames']} frames at {stats['size'][0]}x{stats['size'][1]} on {stats['gl_renderer']}: "
          f"{paced}{timed}processor ({stats['processor_path']}) {stats['passes_ms'].get('process', 0)} ms; "
          f"{stats['drawn']['meshes']:,} agents drawn as meshes and {stats['drawn']['impostors']:,} as impostors, "
          f"{stats['last_frame']['triangles']:,} triangles; NaN rows {stats['nan_count']}")
    w = stats["weapons"]
    if w["enabled"]:
        error = "no weapon drawn" if stats["weapon_error_mm"] is None else f"weapon-to-hand error {stats['weapon_error_mm']} mm"
        # The pose lag is simulated time: the read-back's frames of latency times their frame time (headless, a
        # fixed step; in the window, the frames as they came, capped at ai.max_dt).
        print(f"weapons: {w['drawn']} drawn, read back {w['latency_frames']} frames late (pose lag {w['pose_lag_ms']} ms: "
              f"{w['latency_frames']} frames x their simulated frame time); {error}; read-back wait median "
              f"{stats['readback_wait_ms']['median']} ms, max {stats['readback_wait_ms']['max']} ms, {w['stalls']} stalls")
    if args.screenshot or args.stats or stats.get("clip_bytes"):
        print("wrote " + " and ".join(str(p) for p in (args.screenshot, args.stats, args.clip if stats.get("clip_bytes") else None) if p))
    return 0


def _cast_flag(text: str) -> list[tuple[str, float]]:
    """--characters' (model, share) pairs: "zombie=3,brute=1,x.glb=0.5" (a share of 1 where none is given)."""
    from crowd.asset.gltf import is_built_in
    from crowd.pipeline_config import PipelineError

    out = []
    for item in text.split(","):
        model, sep, share = item.strip().rpartition("=") if "=" in item else (item.strip(), "", "1")
        model = model.strip()
        try:
            value = float(share)
        except ValueError:
            value = None
        if not model or value is None:
            raise PipelineError(f"--characters: each character is MODEL=SHARE (zombie=3,brute=1), got {item.strip()!r}")
        if not is_built_in(model) and not Path(model).is_file():
            raise PipelineError(f"--characters: {model}: no such file (nor a built-in: zombie, brute)")
        out.append((model, value))
    return out


def _headless_defaults(args) -> None:
    """Headless runs stop by themselves and leave a picture: 60 frames and out/demo.png unless given."""
    from crowd.settings import DEFAULTS

    args.frames = DEFAULTS["frames"] if args.frames is None else args.frames
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
