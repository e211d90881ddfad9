"""What joint scale costs the animation processor (issue 44, point 1's target: at most 1.1 times): the
built-in zombie's bake as it is (no scale texture, HAS_SCALE compiled out), the same bake with a scale
texture of ones (a character with uniform scale keys: the texture sampled and blended, the affine
composed with it), and with a residual texture of ones as well (non-uniform scale: HAS_RESIDUAL, each
joint's own matrix scaled), on both processor paths, interleaved in one run, GPU timer queries, medians.

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
    uneven = dataclasses.replace(scaled, residual=np.ones((plain.rows, zombie.skeleton.joint_count, 3), np.float32))
    paths = ["compute", "fragment"] if has_compute(ctx) else ["fragment"]
    rng = np.random.default_rng(1)
    query = ctx.query(time=True)
    rows = []
    print(f"{info['gl_renderer']} | {info['gl_version']} | {device_cpu()} | 4 layers | median of {args.frames} frames")
    for n in (int(x) for x in args.agents.split(",")):
        layers = random_layers(n, 4, len(plain.clips), rng)
        for path in paths:
            procs = {name: AnimationProcessor(ctx, bake, 4, path=path) for name, bake in (("plain", plain), ("scale", scaled), ("uneven", uneven))}
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
            plain_ms, scale_ms, uneven_ms = (float(np.median(samples[k])) for k in ("plain", "scale", "uneven"))
            rows.append({"agents": n, "path": path, "plain_ms": round(plain_ms, 4), "scale_ms": round(scale_ms, 4),
                         "ratio": round(scale_ms / plain_ms, 3), "non_uniform_ms": round(uneven_ms, 4),
                         "non_uniform_ratio": round(uneven_ms / plain_ms, 3)})
            print(f"{n:>9} {path:>9}  without scale {plain_ms:8.3f} ms  uniform {scale_ms:8.3f} ms ({scale_ms / plain_ms:.3f})  "
                  f"non-uniform {uneven_ms:8.3f} ms ({uneven_ms / plain_ms:.3f})")
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(args.json, json.dumps({"device": f"{info['gl_renderer']}, {info['gl_version']}", "rows": rows}, indent=1).encode())
    ctx.release()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
