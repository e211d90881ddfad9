"""What joint scale costs the animation processor (issue 44, point 1's target: at most 1.1 times): the
built-in zombie's bake as it is (no scale texture, HAS_SCALE compiled out), the same bake with a scale
texture of ones (a character with uniform scale keys: the texture sampled and blended, the affine
composed with it), and with non-uniform scale on every leaf joint and on every joint (HAS_RESIDUAL: the
joints that have it blend it for their own matrix), on both processor paths, interleaved in one run, GPU
timer queries, medians.

Run: python -m bench.scale_cost [--agents 16384,131072,1048576] [--frames 30] [--json out.json]"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np

from crowd.anim.processor import AnimationProcessor
from crowd.anim.roles import bake_roles, match_roles
from crowd.asset.gltf import load_character
from crowd.gl import describe, has_compute, headless_context

from .common import device_cpu, random_layers


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--agents", default="16384,131072,1048576")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--json")
    args = p.parse_args(argv)
    ctx = headless_context()
    info = describe(ctx)
    zombie = load_character(None)
    roles, _ = match_roles(zombie.clips)
    plain = bake_roles(zombie, roles)
    scaled = dataclasses.replace(plain, scale=np.ones((plain.rows, zombie.skeleton.joint_count), np.float32))
    # Non-uniform scale on every leaf joint (the hands, feet, head and the like: where a file's stretch
    # usually is), and on every joint (the worst case).
    jc = zombie.skeleton.joint_count
    leaves = np.setdiff1d(np.arange(jc), zombie.skeleton.parents[zombie.skeleton.parents >= 0])
    stretch = np.ones((plain.rows, jc, 3), np.float32)
    stretch[:, leaves] = (1.2, 1.0, 0.8)
    uneven = dataclasses.replace(scaled, residual=stretch)
    everywhere = dataclasses.replace(scaled, residual=np.tile(np.float32([1.2, 1.0, 0.8]), (plain.rows, jc, 1)))
    paths = ["compute", "fragment"] if has_compute(ctx) else ["fragment"]
    rng = np.random.default_rng(1)
    query = ctx.query(time=True)
    rows = []
    print(f"{info['gl_renderer']} | {info['gl_version']} | {device_cpu()} | 4 layers | median of {args.frames} frames")
    for n in (int(x) for x in args.agents.split(",")):
        layers = random_layers(n, 4, len(plain.clips), rng)
        for path in paths:
            procs = {name: AnimationProcessor(ctx, bake, 4, path=path)
                     for name, bake in (("plain", plain), ("scale", scaled), ("uneven", uneven), ("everywhere", everywhere))}
            try:
                samples = {name: [] for name in procs}
                for proc in procs.values():
                    proc.resize(n)
                    proc.upload(layers)
                for frame in range(args.frames + 2):
                    for name, proc in procs.items():  # interleaved: the same GPU state for both
                        proc.upload(layers)  # (a run processes what was uploaded since the last)
                        with query:
                            proc.run()
                        if frame >= 2:
                            samples[name].append(query.elapsed / 1e6)
            finally:
                for proc in procs.values():
                    proc.release()
            plain_ms, scale_ms, uneven_ms, all_ms = (float(np.median(samples[k])) for k in ("plain", "scale", "uneven", "everywhere"))
            rows.append({"agents": n, "path": path, "plain_ms": round(plain_ms, 4), "scale_ms": round(scale_ms, 4),
                         "ratio": round(scale_ms / plain_ms, 3), "leaves_non_uniform_ms": round(uneven_ms, 4),
                         "leaves_non_uniform_ratio": round(uneven_ms / plain_ms, 3), "all_non_uniform_ms": round(all_ms, 4),
                         "all_non_uniform_ratio": round(all_ms / plain_ms, 3)})
            print(f"{n:>9} {path:>9}  without scale {plain_ms:7.3f} ms  uniform {scale_ms / plain_ms:.3f}  "
                  f"non-uniform leaves {uneven_ms / plain_ms:.3f}  every joint {all_ms / plain_ms:.3f}")
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(args.json, json.dumps({"device": f"{info['gl_renderer']}, {info['gl_version']}", "rows": rows}, indent=1).encode())
    ctx.release()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
