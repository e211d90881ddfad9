"""crowd-bench morph: what morph targets cost the processor and the skinned draw (issue 23's targets).

The built-in zombie's crowd on the benchmarks' grid, every agent at LOD0 (no culling, no shadows: the
draw is geometry-bound, as in ``crowd-bench scale``), drawn through the cull path the demo takes there,
in configurations built side by side and measured in alternation, round after round:
- ``off``: no morph bake: the processor writes no pairs, the draw has no morph code; ``off again``, the
  same built a second time, shows what separates two identical configurations in this run (the noise
  floor "nothing measurable" is judged against);
- ``k active`` (k = 0, 1, 2, 4): every agent moves exactly k targets (a morph bake whose tracks are all
  0 and whose variation gives the first k targets a weight of 1 each), so the draw runs the morph code
  and fetches k deltas for each vertex a target moves (from storage buffers on GL 4.3, and ``4 in tex``
  from textures, as a GL 3.3 context draws them); with 0 active the GPU cull lists every agent in the
  plain twins (crowd.draw.gpu_cull), and ``0 active, unrouted`` keeps them in the morph draws (the
  cull not given the processor), as the CPU cull path does.
Reported: the median GPU ms of the processor and of the colour pass per configuration, and the colour
pass's cost against ``off``, per active target, and the share of the LOD0 vertices the targets move.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from .common import device_cpu, grid_crowd, random_layers

ACTIVE = (0, 1, 2, 4)  # the built-in zombie has 4 targets


def _morph_bake(character, joints, active: int):
    from crowd.anim.morph import MorphBake

    m = len(character.morphs)
    variation = np.zeros((m, 2), np.float32)
    variation[:active] = 1.0
    return MorphBake(tuple(character.morphs), np.zeros((1, m), np.float32), np.tile(np.array([[0, 1]], np.int32), (len(joints.clips), 1)),
                     variation, 0)


def _check_routing(name: str, active, renderer) -> None:
    """That each configuration draws what it says: its agents all in the morph draws where they move
    targets (or are not routed), all in the plain twins where they move none."""
    renderer.refresh_counts(wait=True)
    morph = sum(d.count for d in renderer.draws if d.morph)
    twins = sum(d.count for d in renderer.draws if d.twin_of is not None)
    want_twins = active == 0 and not name.endswith("unrouted")
    if active is not None and (bool(twins) != want_twins or bool(morph) == want_twins):
        raise SystemExit(f"{name}: {morph} instances in the morph draws and {twins} in their plain twins; the configuration wants "
                         f"{'the twins' if want_twins else 'the morph draws'}")


def bench_morph(args) -> int:
    import moderngl

    from crowd.anim.bake import bake
    from crowd.anim.roles import clips_used, match_roles
    from crowd.asset.gltf import load_character
    from crowd.frame import Instances
    from crowd.gl import Offscreen, describe, has_compute, headless_context
    from crowd.progress import steps
    from crowd.settings import parse
    from crowd.draw.render import CrowdRenderer
    from crowd.stages import StageSpec, Stages, cull_path

    size = parse("size", args.size)
    n = int(args.agents)
    ctx = headless_context()
    info = describe(ctx)
    character = load_character()
    roles, _ = match_roles(character.clips)
    clips = [character.clip(c) for c in clips_used(roles)]
    if len(character.morphs) < max(ACTIVE):
        raise SystemExit(f"the built-in zombie has {len(character.morphs)} morph targets; this benchmark needs {max(ACTIVE)}")
    compute = has_compute(ctx)
    spec = StageSpec(layers=4, processor_path="compute" if compute else "fragment", lod_distances=(1e9, 1e9, 1e9), shadows=False,
                     culling=False, cull="auto", foot_lock=False)
    configs = {"off": None, "off again": None, **{f"{k} active": k for k in ACTIVE}, "0 active, unrouted": 0}
    if compute:  # the deltas in textures, as a GL 3.3 context draws them, beside the storage buffers GL 4.3 uses
        configs["4 in tex"] = ACTIVE[-1]
    rng = np.random.default_rng(1)
    pos, camera = grid_crowd(n, size[0] / size[1])
    lod0 = [m for m in character.meshes if m.lod == 0]
    moved = sum(int(np.count_nonzero(np.any(m.morph_positions != 0, axis=(0, 2)))) for m in lod0 if m.morph_count)
    share = moved / sum(len(m.positions) for m in lod0)
    built: dict[str, Stages] = {}
    query = ctx.query(time=True)

    def gpu_ms(fn):
        with query:
            fn()
        return query.elapsed / 1e6

    print(f"{info['gl_renderer']} | {info['gl_version']} | {size[0]}x{size[1]} | {n:,} agents at LOD0 | {args.rounds} rounds of "
          f"{args.frames} frames, configurations alternated | targets move {share:.1%} of the LOD0 vertices")
    samples = {name: {"proc": [], "draw": []} for name in configs}
    try:
        for name, active in configs.items():
            joints = bake(character.skeleton, clips)
            if active is not None:
                joints.morphs = _morph_bake(character, joints, active)
            built[name] = Stages.build(ctx, (character, joints), spec, n)
            if name.endswith("in tex"):
                built[name].replace("renderer", CrowdRenderer(ctx, character, lod_distances=spec.lod_distances, shadows=False, culling=False,
                                                             cull_path=cull_path(ctx, spec.cull), morphs=[True], morph_buffers=False))
        heads = built["off"].renderer.groups[0].get("head", [])
        inst = Instances(pos, rng.uniform(-3, 3, n).astype(np.float32), np.ones(n, np.float32), np.full((n, 4), 200, np.uint8),
                         {"head": rng.integers(0, len(heads), n)} if heads else {})
        layers = random_layers(n, 4, len(clips), rng)
        with Offscreen(ctx, size) as target:
            fb = target.framebuffer
            for rnd in steps(range(args.rounds), desc="morph", unit="round"):
                for name, stages in built.items():
                    proc, renderer = stages.processor, stages.renderer
                    for frame in range(args.frames + 1):
                        proc.upload(layers)
                        p_ms = gpu_ms(proc.run)
                        view = renderer.prepare(camera, inst, proc.row_offset(0), palette=proc.layout,
                                                processor=None if name.endswith("unrouted") else proc)
                        fb.use()
                        fb.clear(0.1, 0.1, 0.1, 1.0, depth=1.0)
                        d_ms = gpu_ms(lambda: renderer.color_pass(fb, view, proc))
                        if rnd == 0 and frame == 0:
                            _check_routing(name, configs[name], renderer)
                        if frame:  # the first of each turn binds and compiles
                            samples[name]["proc"].append(p_ms)
                            samples[name]["draw"].append(d_ms)
            ctx.finish()
    finally:
        for stages in built.values():
            stages.release()
    rows = []
    base = float(np.median(samples["off"]["draw"]))
    print(f"{'config':>18} {'proc ms':>9} {'draw ms':>9} {'draw / off':>11} {'ms per target':>14}")
    for name, active in configs.items():
        p, d = float(np.median(samples[name]["proc"])), float(np.median(samples[name]["draw"]))
        row = {"config": name, "active": active, "processor_ms": round(p, 4), "draw_ms": round(d, 4), "draw_ratio": round(d / base, 4)}
        if active:
            zero = float(np.median(samples["0 active"]["draw"]))
            row["draw_ms_per_target"] = round((d - zero) / active, 4)
            row["storage"] = "textures" if name.endswith("in tex") or not compute else "buffers"
        rows.append(row)
        print(f"{name:>18} {p:>9.3f} {d:>9.3f} {d / base:>11.3f} {row.get('draw_ms_per_target', float('nan')):>14.4f}")
    if args.json:
        from crowd.files import atomic_write_bytes

        device = f"{info['gl_renderer']}, {info['gl_version']}; {device_cpu()}; moderngl {moderngl.__version__}"
        atomic_write_bytes(Path(args.json), json.dumps({"device": device, "size": list(size), "agents": n, "rounds": args.rounds,
                                                        "frames": args.frames, "moved_share": share, "rows": rows,
                                                        "date": time.strftime("%Y-%m-%d")}, indent=1).encode())
    ctx.release()
    return 0
