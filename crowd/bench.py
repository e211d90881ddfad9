"""``crowd-bench``: reproducible measurements. Each subcommand prints a table and can write JSON.

- ``bake``: the bake's size and its joint-position error against the float64 reference, per clip and
  bake rate (CPU only: this is about the data, not the GPU).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np


def _device_cpu() -> str:
    import numpy

    return f"{platform.processor() or platform.machine()} ({platform.system()}), Python {platform.python_version()}, numpy {numpy.__version__}"


def bench_bake(args) -> int:
    from .bake import bake, joint_position_error
    from .gltf import load_character

    character = load_character(args.model)
    rates = [int(r) for r in args.rates.split(",")]
    phases = np.linspace(0.0, 1.0, args.samples)
    rows = []
    for precision in ("f32", "f16"):
        for fps in rates:
            t0 = time.perf_counter()
            b = bake(character.skeleton, character.clips, fps, precision)
            bake_ms = (time.perf_counter() - t0) * 1e3
            for clip in character.clips:
                err = joint_position_error(b, character.skeleton, clip, phases)
                rows.append({"clip": clip.name, "duration_s": round(clip.duration, 4), "loop": clip.loop, "bake_fps": fps,
                             "precision": precision, "frames": b.clips[b.clip_index(clip.name)].frame_count,
                             "max_joint_error_mm": round(float(err.max()) * 1e3, 4), "bytes_all_clips": b.nbytes,
                             "bake_ms_all_clips": round(bake_ms, 2)})
    print(f"{character.name}: {character.skeleton.joint_count} joints, {len(character.clips)} clips; "
          f"max joint position error over {args.samples} phases per clip, against the float64 reference")
    print(f"{'clip':<14}{'len s':>7}  " + "  ".join(f"{p} {r:>2}fps".rjust(12) for p in ("f32", "f16") for r in rates))
    for clip in character.clips:
        cells = [next(x for x in rows if x["clip"] == clip.name and x["bake_fps"] == r and x["precision"] == p)["max_joint_error_mm"]
                 for p in ("f32", "f16") for r in rates]
        print(f"{clip.name:<14}{clip.duration:>7.3f}  " + "  ".join(f"{c:>9.3f} mm" for c in cells))
    for p in ("f32", "f16"):
        print(f"bytes ({p}): " + ", ".join(f"{r} fps {next(x for x in rows if x['bake_fps'] == r and x['precision'] == p)['bytes_all_clips']}" for r in rates))
    if args.json:
        from .gltf_write import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps({"device": _device_cpu(), "model": str(args.model or "built-in zombie"),
                                                        "rows": rows}, indent=1).encode())
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="crowd-bench", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("bake", help="bake size and error against the float64 reference")
    p.add_argument("--model", type=Path, help="a .glb/.gltf (default: the built-in zombie)")
    p.add_argument("--rates", default="15,30,60")
    p.add_argument("--samples", type=int, default=1201, help="phases per clip at which the error is measured")
    p.add_argument("--json", type=Path)
    p.set_defaults(run=bench_bake)
    args = parser.parse_args(argv)
    from .gltf import GltfImportError
    from .bake import BakeError

    try:
        return args.run(args)
    except (GltfImportError, BakeError) as exc:
        print(f"crowd-bench: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
