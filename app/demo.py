"""``crowd-demo``: the demo entry point. Thin: it parses flags and calls the stages.

At this stage of the project (foundation issue) the GPU processor and the window are not built yet,
so the demo imports the character, bakes the requested clips, reports what it baked and how far the
bake is from the float64 reference, and renders a CPU-skinned contact sheet through headless EGL.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="crowd-demo", description="Zombie crowd demo (foundation stage).")
    parser.add_argument("--model", type=Path, help="a skinned .glb/.gltf (default: the built-in zombie)")
    parser.add_argument("--clips", nargs="*", help="clips to bake (default: all)")
    parser.add_argument("--bake-fps", type=float, default=15.0)
    parser.add_argument("--precision", choices=["f32", "f16"], default="f32")
    parser.add_argument("--screenshot", type=Path, default=Path("out/demo.png"))
    parser.add_argument("--headless", action="store_true", help="no window even when a display exists")
    args = parser.parse_args(argv)

    from crowd.bake import BakeError, bake, joint_position_error
    from crowd.gl import GLUnavailable, has_display
    from crowd.gltf import GltfImportError, load_character
    from crowd.preview import render_sheet

    if not args.headless:
        reason = "no display found" if not has_display() else "the interactive window is not built yet (issue 6)"
        print(f"crowd-demo: {reason}; running headless (EGL) instead.")
    try:
        character = load_character(args.model, args.clips)
        baked = bake(character.skeleton, character.clips, args.bake_fps, args.precision)
    except (GltfImportError, BakeError) as exc:
        print(f"crowd-demo: {exc}", file=sys.stderr)
        return 2
    for w in character.warnings + baked.warnings:
        print(f"  note: {w}")
    print(f"{character.name}: {character.skeleton.joint_count} joints, {len(character.meshes)} skinned meshes, "
          f"{len(character.clips)} clips baked at {args.bake_fps:g} fps ({args.precision}), {baked.rows} rows, {baked.nbytes} bytes")
    phases = np.linspace(0.0, 1.0, 241)
    for clip in character.clips:
        err = joint_position_error(baked, character.skeleton, clip, phases).max()
        info = baked.clips[baked.clip_index(clip.name)]
        print(f"  {clip.name:<16} {clip.duration:6.3f} s  {'loop' if clip.loop else 'once'}  {info.frame_count:4d} frames  "
              f"max joint error {err * 1e3:8.3f} mm")
    try:
        pieces = ("body", "head_a", "shirt_torn") if args.model is None else ()
        render_sheet(character, [c.name for c in character.clips], 6, 160, args.screenshot, 0.8, pieces)
    except GLUnavailable as exc:
        print(f"crowd-demo: {exc}", file=sys.stderr)
        return 3
    print(f"wrote {args.screenshot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
