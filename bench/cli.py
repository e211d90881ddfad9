"""``crowd-bench``: reproducible measurements. Each subcommand prints a table and can write JSON.

- ``bake``: the bake's size and its joint-position error against the float64 reference, per clip and
  bake rate (CPU only: this is about the data, not the GPU).
- ``ai``: ms per crowd-AI step (one 1/60 s substep plus writing the processor's layers) against agent
  count: the numpy AI on the CPU and the compute passes on the GPU, side by side (bench/ai_report.py).
- ``circles``: FLAME GPU 2's circles workload on this project's GPU grid (bench/circles.py).
- ``scale``: GPU ms of the animation processor and of the skinned instanced draw against agent count,
  with the unskinned instanced draw of the same meshes measured in the same run as the ceiling.
- ``error``: the processor's error against its run time for every bake rate, storage and
  interpolation, with the Pareto front, the default it picks and the stiff and extreme cases
  (bench/error_report.py); ``plot-error`` redraws its plot from the JSON.
- ``frame``: the whole headless frame's period (frames back to back, one finish at the end) and latency
  (one finish per frame), with the pass medians, against agent count; ``--panel`` adds the panel and
  HUD drawn into the frame, side by side.
- ``morph``: the processor's and the skinned draw's GPU ms with morph targets off and 0 to 4 active (bench/morph_cost.py).
- ``impostor``: the impostor atlas's error against the mesh, its bytes and bake time, over a grid of atlas settings (bench/impostor_quality.py).
- ``soak``: the default scene for many frames: resident memory, live GL objects and faults (bench/soak.py).
- ``meshopt``: import time of meshopt-compressed files and the decoder's throughput (bench/meshopt_decode.py).
- ``readback``: the weapons' socket gather and GPU→CPU transfer against the number of armed agents,
  the CPU's wait on it, and the weapon-to-hand error with the body drawn in step with the read-back
  (sync) and from the newest palette (unsync), side by side in one run.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from crowd.progress import steps

from .ai_report import bench_agreement, bench_ai
from .circles import bench_circles
from .frame_bench import bench_frame
from .common import device_cpu, grid_crowd, random_layers


def bench_bake(args) -> int:
    from crowd.anim.bake import bake, joint_position_error
    from crowd.asset.gltf import load_character

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
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps({"device": device_cpu(), "model": str(args.model or "built-in zombie"),
                                                        "rows": rows}, indent=1).encode())
    return 0


def bench_scale(args) -> int:
    """Every agent at LOD0, no culling, no shadows: the draw is geometry-bound, so the unskinned draw of
    the same meshes and instances is the ceiling the skinned draw is compared with."""
    import moderngl

    from crowd.anim.roles import bake_roles, match_roles
    from crowd.asset.gltf import load_character
    from crowd.frame import Instances
    from crowd.gl import Offscreen, describe, has_compute, headless_context
    from crowd.settings import parse
    from crowd.stages import StageSpec, Stages, build_processor

    size = parse("size", args.size)
    counts = [int(x) for x in args.agents.split(",")]
    ctx = headless_context()
    info = describe(ctx)
    character = load_character(args.model)
    roles, _ = match_roles(character.clips)
    baked = bake_roles(character, roles)
    compute = has_compute(ctx)
    # The CPU cull path: its triangle count is known at once, and the draw itself is the same instanced
    # draw (the GPU path only adds the cull pass and reads the count from an indirect command).
    spec = StageSpec(layers=args.layers, processor_path="compute" if compute else "fragment", lod_distances=(1e9, 1e9, 1e9),
                     shadows=False, culling=False, cull="cpu")
    rng = np.random.default_rng(1)
    rows = []
    print(f"{info['gl_renderer']} | {info['gl_version']} | {size[0]}x{size[1]} | {args.layers} layers | median of {args.frames} frames")
    print(f"{'agents':>8} {'proc ms':>8} {'frag ms':>8} {'draw ms':>8} {'frame ms':>9} {'Mtri/s':>8} {'ceil Mtri/s':>11} {'ratio':>6}")
    with Stages.build(ctx, (character, baked), spec) as stages, Offscreen(ctx, size) as target:
        renderer, main_proc = stages.renderer, stages.processor
        # The fragment path beside the compute path, measured in the same run (without GL 4.3 it is the main one).
        fragment = Stages(processor=build_processor(ctx, (character, baked), dataclasses.replace(spec, processor_path="fragment"))) if compute else Stages()
        with fragment:
            processors = {"compute": main_proc, "fragment": fragment.processor} if compute else {"fragment": main_proc}
            fb = target.framebuffer
            query = ctx.query(time=True)

            def gpu_ms(fn):
                with query:
                    fn()
                return query.elapsed / 1e6

            for n in steps(counts, desc="scale", unit="size"):
                pos, camera = grid_crowd(n, size[0] / size[1])
                heads = renderer.groups[0].get("head", [])
                inst = Instances(pos, rng.uniform(-3, 3, n).astype(np.float32), np.ones(n, np.float32), np.full((n, 4), 200, np.uint8),
                                 {"head": rng.integers(0, len(heads), n)} if heads else {})
                layers = random_layers(n, args.layers, len(baked.clips), rng)
                for proc in processors.values():
                    proc.resize(n)
                    proc.upload(layers)
                view = renderer.prepare(camera, inst)
                tris = renderer.last["triangles"]
                samples = {"proc": [], "frag": [], "draw": [], "ceil": [], "frame": []}
                for frame in range(args.frames + 2):
                    t0 = time.perf_counter()
                    main_proc.upload(layers)
                    renderer.prepare(camera, inst)
                    fb.use()
                    fb.clear(0.1, 0.1, 0.1, 1.0, depth=1.0)
                    p_ms = gpu_ms(main_proc.run)
                    d_ms = gpu_ms(lambda: renderer.color_pass(fb, view, main_proc, skinned=True))
                    ctx.finish()
                    f_ms = (time.perf_counter() - t0) * 1e3
                    fb.clear(0.1, 0.1, 0.1, 1.0, depth=1.0)
                    c_ms = gpu_ms(lambda: renderer.color_pass(fb, view, main_proc, skinned=False))
                    fr_ms = gpu_ms(processors["fragment"].run) if compute else p_ms
                    if frame >= 2:  # the first frames compile and upload
                        for k, v in (("proc", p_ms), ("frag", fr_ms), ("draw", d_ms), ("ceil", c_ms), ("frame", f_ms)):
                            samples[k].append(v)
                med = {k: float(np.median(v)) for k, v in samples.items()}
                row = {"agents": n, "triangles": tris, "processor_ms": round(med["proc"], 4), "processor_fragment_ms": round(med["frag"], 4),
                       "draw_ms": round(med["draw"], 4), "frame_ms": round(med["frame"], 3),
                       "tris_per_s": round(tris / (med["draw"] / 1e3)), "ceiling_ms": round(med["ceil"], 4),
                       "ceiling_tris_per_s": round(tris / (med["ceil"] / 1e3))}
                row["ratio"] = round(row["tris_per_s"] / row["ceiling_tris_per_s"], 3)
                rows.append(row)
                print(f"{n:>8} {row['processor_ms']:>8.3f} {row['processor_fragment_ms']:>8.3f} {row['draw_ms']:>8.3f} {row['frame_ms']:>9.2f} "
                      f"{row['tris_per_s'] / 1e6:>8.0f} {row['ceiling_tris_per_s'] / 1e6:>11.0f} {row['ratio']:>6.3f}")
    if args.json:
        from crowd.files import atomic_write_bytes

        device = f"{info['gl_renderer']}, {info['gl_version']}; {device_cpu()}; moderngl {moderngl.__version__}"
        atomic_write_bytes(Path(args.json), json.dumps({"device": device, "size": list(size), "layers": args.layers,
                                                        "model": str(args.model or "built-in zombie"), "rows": rows}, indent=1).encode())
    ctx.release()
    return 0


def bench_lod(args) -> int:
    """Silhouette IoU of each coarser LOD against LOD0 at its switch distance (bench/lod_silhouette.py).
    A character whose file has no coarser LODs gets them made (crowd/asset/lod.py, without the cache,
    timed: the median of --repeats runs) and is measured at its own switch distances."""
    from crowd.asset.gltf import load_character
    from crowd.settings import DEFAULTS, parse

    from .lod_silhouette import generated_lods, silhouette_iou

    character = load_character(args.model)
    pixels = parse("lod_error_px", args.lod_error_px) if args.lod_error_px else DEFAULTS["lod_error_px"]
    character, seconds = generated_lods(character, args.repeats)
    if args.lod_distances:
        distances = parse("lod_distances", args.lod_distances)
    elif character.lod_distances:
        distances = tuple(d / pixels for d in character.lod_distances)
    else:
        distances = DEFAULTS["lod_distances"]
    size = parse("size", args.size)
    rows = silhouette_iou(character, distances, size)
    made = f", LODs made in {np.median(seconds):.2f} s (median of {len(seconds)})" if seconds else ""
    print(f"{character.name}: silhouettes at {size[0]}x{size[1]}, 45-degree camera, {rows[0]['views'] if rows else 0} views per LOD{made}")
    print(f"{'LOD':>4} {'from m':>7} {'height px':>10} {'triangles':>14} {'IoU min / mean (samples)':>25} {'(pixels)':>16}")
    for r in rows:
        print(f"{r['lod']:>4} {r['distance_m']:>7.3g} {r['height_px']:>10.1f} {r['triangles']:>6} / {r['triangles_lod0']:<6} "
              f"{r['iou_min']:>16.4f} / {r['iou_mean']:.4f} {r['pixel_iou_min']:>9.4f} / {r['pixel_iou_mean']:.4f}")
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps({"model": str(args.model or "built-in zombie"), "size": list(size),
                                                        "lod_distances": [float(d) for d in distances], "lod_error_px": pixels, "own_distances": character.lod_distances is not None,
                                                        "generation_s": [round(t, 3) for t in seconds], "rows": rows}, indent=1).encode())
    return 0


def bench_simplifiers(args) -> int:
    """crowd's simplifier against fast-simplification, pyfqmr and meshoptimizer on the LODs made for a
    file without them (bench/simplifier_compare.py): triangles, silhouette IoU at the switch distances, time."""
    from crowd.asset.gltf import load_character
    from crowd.settings import parse

    from .simplifier_compare import WIDE_UV, compare

    out = compare(load_character(args.model), parse("size", args.size))
    for line in out["missing"]:
        print(f"crowd-bench simplifiers: {line}", file=sys.stderr)
    print(f"{out['character']}: LODs from {' / '.join(f'{d:.3g}' for d in out['lod_distances'])} m; IoU min / mean at each LOD's distance; "
          f"uv: triangles across more than {WIDE_UV:g} of the texture (LOD0: {out['wide_uv_lod0']})")
    for name, c in out["candidates"].items():
        cells = "  ".join(f"LOD{r['lod']} {r['triangles']:>5} tris {r['iou_min']:.4f} / {r['iou_mean']:.4f} uv {r['wide_uv']}" for r in c["rows"])
        print(f"{name:<20} {c['seconds']:>7.2f} s  {cells}")
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps(out, indent=1).encode())
    return 0


def bench_vertex_cache(args) -> int:
    """The hand-written triangle order against meshoptimizer's (bench/vertex_cache_compare.py)."""
    try:
        import meshoptimizer  # noqa: F401
    except ImportError:
        print("crowd-bench vertex-cache: meshoptimizer is not importable (it ships no wheel: build its sdist, see docs/BENCHMARKS.md)",
              file=sys.stderr)
        return 2
    from crowd.asset.gltf import load_character

    from .vertex_cache_compare import compare

    out = compare(load_character(args.model))
    print(f"{'mesh':<26} {'tris':>6}  shaded per triangle, batches of 32: source / hand / meshoptimizer")
    for r in out["meshes"]:
        print(f"{r['mesh']:<26} {r['triangles']:>6}  " + " / ".join(f"{r[k]['batch32_shaded_per_triangle']:.4f}" for k in ("source", "hand", "meshoptimizer")))
    t = out["total"]
    print("all meshes (per triangle): " + ", ".join(f"{k} {t[k]['batch32_shaded_per_triangle']:.4f} (FIFO-32 {t[k]['fifo32_misses_per_triangle']:.4f})"
                                                 for k in ("source", "hand", "meshoptimizer")) + f"; ms {t['ms']}")
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps(out, indent=1).encode())
    return 0


def bench_impostor(args) -> int:
    """The impostor atlas's quality against its bytes (bench/impostor_quality.py)."""
    from .impostor_quality import bench_impostor as run

    return run(args)


def bench_morph(args) -> int:
    """What morph targets cost the processor and the skinned draw (bench/morph_cost.py)."""
    from .morph_cost import bench_morph as run

    return run(args)


def bench_soak(args) -> int:
    """The game as shipped for many frames: resident memory, live GL objects and faults (bench/soak.py)."""
    from crowd.files import atomic_write_bytes
    from crowd.progress import bar
    from crowd.settings import parse

    from .soak import run_soak

    size = parse("size", args.size)

    def partial(samples):  # a long soak stopped early still leaves its samples
        if args.json:
            atomic_write_bytes(Path(args.json), json.dumps({"partial": True, "samples": samples}, indent=1).encode())

    with bar(args.frames, f"soak, {args.agents:,} agents", "frame") as shown:
        result = run_soak(args.agents, args.frames, size, args.warmup, args.every, args.scene, progress=shown, on_sample=partial, heap=args.heap)
    if args.json:
        atomic_write_bytes(Path(args.json), json.dumps(result, indent=1).encode())
    print(f"{result['device']} | {result['agents']:,} agents, {result['frames']:,} frames at {size[0]}x{size[1]} in {result['seconds']} s, "
          f"{result['rounds']} rounds")
    rss, gl = result["rss_mb"], result["gl_objects"]
    if rss is None:  # a fault before the first sample
        print("no sample taken: the run ended before its warm-up did")
    else:
        print(f"after {result['warmup']} frames, {len(result['samples'])} samples: resident memory {rss['first']} MB to {rss['last']} MB "
              f"(drift {100 * rss['drift']:+.2f} %, growth {100 * rss['growth']:+.2f} %; range {rss['min']} to {rss['max']} MB, spread {100 * rss['spread']:.2f} %; "
              f"untrimmed drift {100 * result['rss_untrimmed_mb']['drift']:+.2f} %, spread {100 * result['rss_untrimmed_mb']['spread']:.2f} %); "
              f"GL objects {gl['first']:.0f} to {gl['last']:.0f} (drift {100 * gl['drift']:+.2f} %, spread {100 * gl['spread']:.2f} %)"
              + (f"; Python heap held {result['heap_mb']['min']} to {result['heap_mb']['max']} MB (rise {result['heap_mb']['rise']:+.2f} MB)" if args.heap else ""))
    print(f"faults {len(result['faults'])}")
    for fault in result["faults"][:20]:
        print(f"  fault: {fault}")
    return 0 if not result["faults"] else 1


def bench_fragment(args) -> int:
    """The fragment processor (GL 3.3 / 4.1) against the compute one, its two passes apart, and the floor of
    any fragment pass over the palette's texels (bench/fragment_probe.py)."""
    from crowd.gl import describe, headless_context

    from .fragment_probe import measure

    ctx = headless_context()
    info = describe(ctx)
    print(f"{info['gl_renderer']} | {info['gl_version']} | 4 layers | GPU ms, median of {args.repeats} runs")
    print(f"{'agents':>8} {'compute':>8} {'fragment':>9} {'locals':>7} {'compose':>8} {'floor 3':>8} {'floor 1':>8} {'frag/comp':>10}")
    rows = measure(ctx, [int(x) for x in args.agents.split(",")], args.repeats)
    for r in rows:
        ratio = r["fragment_ms"] / r["compute_ms"] if r.get("compute_ms") else float("nan")
        print(f"{r['agents']:>8} {r.get('compute_ms', float('nan')):>8.3f} {r['fragment_ms']:>9.3f} {r['locals_ms']:>7.3f} {r['compose_ms']:>8.3f} "
              f"{r['floor_3_targets_ms']:>8.3f} {r['floor_1_target_ms']:>8.3f} {ratio:>10.1f}")
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps({"device": f"{info['gl_renderer']}, {info['gl_version']}", "rows": rows}, indent=1).encode())
    return 0


def bench_feedback(args) -> int:
    """The transform-feedback cull (GL 4.0 to 4.2) against the compute one, its counting spread less, and its
    feedback draws alone (bench/feedback_probe.py)."""
    from crowd.gl import describe, headless_context

    from .feedback_probe import VARIANTS, floor, measure

    ctx = headless_context()
    info = describe(ctx)
    print(f"{info['gl_renderer']} | {info['gl_version']} | the zombie, shadows, a 2 m fade | the cull's GPU ms, median of {args.repeats} runs")
    print(f"{'agents':>8} {'listed':>8} {'lists':>6} {'draws':>6} " + " ".join(f"{n:>20}" for n in VARIANTS))
    rows = measure(ctx, [int(x) for x in args.agents.split(",")], args.repeats) if args.agents else []
    for r in rows:
        print(f"{r['agents']:>8} {r.get('feedback_listed', 0):>8} {r.get('lists', 0):>6} {r.get('feedback_draws', 0):>6} "
              + " ".join(f"{r.get(n + '_ms', float('nan')):>20.3f}" for n in VARIANTS))
    floors = floor(ctx, args.floor) if args.floor else {}
    if floors:
        print(f"a draw of {args.floor:,} points, a quarter kept, GPU ms: " + ", ".join(f"{k[:-3]} {v:.3f}" for k, v in floors.items() if k != "points"))
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps({"device": f"{info['gl_renderer']}, {info['gl_version']}", "rows": rows, "floor": floors},
                                                       indent=1).encode())
    return 0


def bench_compaction(args) -> int:
    """The GPU cull's compacted lists: GPU ms, entries, bytes an agent (checked against the numpy cull)."""
    from crowd.draw.render import CrowdRenderer
    from crowd.gl import describe, has_compute, headless_context
    from crowd.pipeline import CrowdPipeline
    from crowd.scene import Scene

    from .compaction_probe import measure

    ctx = headless_context()
    if not has_compute(ctx):
        print("crowd-bench compaction: the GPU cull needs GL 4.3 compute shaders", file=sys.stderr)
        return 2
    info = describe(ctx)
    rows = []
    print(f"{info['gl_renderer']} | the demo camera, default scene without weapons | median of {args.repeats} runs")
    for n in steps([int(x) for x in args.agents.split(",")], desc="compaction", unit="size"):
        with CrowdPipeline(ctx, Scene(town=False).with_overrides(agents=n, weapons=False, cull="gpu").pipeline_config()) as pipeline:
            pipeline.camera = pipeline.overview_camera(16 / 9)
            r = pipeline.renderer
            cpu = None
            if n <= args.check:
                cpu = CrowdRenderer(ctx, r.cast, lod_distances=r.lod_distances, shadows=r.shadows, cull_path="cpu", morphs=r.morphs,
                                    impostors=[None if t is None else t.atlas for t in r.impostors], impostor_distance=r.impostor_distance,
                                    lod_fade=r.lod_fade)
            try:
                row = measure(ctx, pipeline, cpu, args.repeats)
            finally:
                if cpu is not None:
                    cpu.release()
        rows.append(row)
        print(f"{n:>8} agents, {row['entries']:>8} entries in {row['lists']} lists x {row['passes']} passes ({row['entries_unlike_the_numpy_cull']} "
              f"unlike the numpy cull's), {row['ms']:.4f} ms, lists {row['list_bytes_per_agent']} B an agent")
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps({"device": info["gl_renderer"], "rows": rows}, indent=1).encode())
    ctx.release()
    return 0


def bench_readback(args) -> int:
    """A 10,000-agent crowd (the AI running, the scripted player striking) in which the first k agents
    are armed. Frames are submitted back to back without glFinish, as a window would, so the read of
    frame F - N overlaps the GPU's work; then a few frames measure the errors (their synchronous
    palette reads would disturb the timing)."""
    from crowd.gl import Offscreen, describe, headless_context
    from crowd.pipeline import CrowdPipeline
    from crowd.pipeline_config import PipelineConfig
    from crowd.settings import parse

    size = parse("size", args.size)
    ctx = headless_context()
    info = describe(ctx)
    device = f"{info['gl_renderer']}, {info['gl_version']}; {device_cpu()}"
    print(f"{device} | {args.agents} agents, {size[0]}x{size[1]}, latency {args.latency} | medians of {args.frames} frames")
    print(f"{'armed':>7} {'gathered':>8} {'gather ms':>10} {'transfer ms':>12} {'wait ms':>8} {'wait max':>9} {'read cpu':>9} "
          f"{'attach':>7} {'sync mm':>9} {'unsync mm':>10}")
    rows = []
    with Offscreen(ctx, size) as target:
        fb = target.framebuffer
        for armed in steps([int(x) for x in args.armed.split(",")], desc="readback", unit="count"):
            with CrowdPipeline(ctx, PipelineConfig(agents=args.agents, seed=args.seed, readback_latency=args.latency)) as pipeline:
                pipeline.camera = pipeline.overview_camera(size[0] / size[1])
                weapons = pipeline.ai.weapon
                weapons[:] = np.where(np.arange(weapons.size) < armed, np.arange(weapons.size) % 2, -1)
                for _ in range(args.warmup):
                    pipeline.frame(fb, 1 / 60)
                ctx.finish()
                pipeline.timer.end_frame(drain=True)
                pipeline.timer.samples.clear()
                pipeline.readback_waits.clear()
                pipeline.readback_stalls = 0
                for _ in range(args.frames):
                    pipeline.frame(fb, 1 / 60)
                ctx.finish()
                pipeline.timer.end_frame(drain=True)
                samples = pipeline.timer.samples
                waits = np.asarray(pipeline.readback_waits or [0.0])
                gathered = pipeline.readback.last_count
                sync = unsync = 0.0
                for _ in range(args.error_frames):
                    pipeline.frame(fb, 1 / 60)
                    sync = max(sync, pipeline.weapon_error_mm() or 0.0)
                    unsync = max(unsync, pipeline.weapon_error_mm(body="latest") or 0.0)

                def med(name):
                    return round(float(np.median(samples[name])), 4) if samples.get(name) else 0.0

                row = {"armed": armed, "gathered": gathered, "gather_ms": med("gather"), "transfer_ms": med("transfer"),
                       "wait_ms": round(float(np.median(waits)), 4), "wait_max_ms": round(float(waits.max()), 4),
                       "stalls": pipeline.readback_stalls, "readback_cpu_ms": med("readback"), "attach_ms": med("attach"),
                       "sync_error_mm": round(sync, 5), "unsync_error_mm": round(unsync, 3)}
                rows.append(row)
                print(f"{armed:>7} {gathered:>8} {row['gather_ms']:>10.4f} {row['transfer_ms']:>12.4f} {row['wait_ms']:>8.4f} "
                      f"{row['wait_max_ms']:>9.4f} {row['readback_cpu_ms']:>9.4f} {row['attach_ms']:>7.3f} {row['sync_error_mm']:>9.5f} "
                      f"{row['unsync_error_mm']:>10.3f}")
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps({"device": device, "agents": args.agents, "latency": args.latency,
                                                        "size": list(size), "rows": rows}, indent=1).encode())
    ctx.release()
    return 0


def build_parser() -> argparse.ArgumentParser:
    """crowd-bench's command line: every subcommand and option, each with its help line."""
    parser = argparse.ArgumentParser(prog="crowd-bench", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("bake", help="bake size and error against the float64 reference")
    p.add_argument("--model", type=Path, help="a .glb/.gltf (default: the built-in zombie)")
    p.add_argument("--rates", default="15,30,60", help='comma-separated bake rates in frames per second')
    p.add_argument("--samples", type=int, default=1201, help="phases per clip at which the error is measured")
    p.add_argument("--json", type=Path, help='write the results as JSON to this file')
    p.set_defaults(run=bench_bake)
    p = sub.add_parser("scale", help="processor and skinned draw GPU ms against agent count, with the unskinned ceiling")
    p.add_argument("--model", type=Path, help="a .glb/.gltf (default: the built-in zombie)")
    p.add_argument("--agents", default="256,1024,4096,16384,65536,131072", help='comma-separated agent counts')
    p.add_argument("--size", default="1920x1080", help='frame size WxH')
    p.add_argument("--frames", type=int, default=10, help='timed frames per agent count (the median is reported)')
    p.add_argument("--layers", type=int, default=4, help='animation layers per agent (1 to 4)')
    p.add_argument("--json", type=Path, help='write the results as JSON to this file')
    p.set_defaults(run=bench_scale)
    p = sub.add_parser("morph", help="GPU ms of the processor and the skinned draw with morph targets: off, and 0 to 4 active an agent")
    p.add_argument("--agents", default="10000", help="agents on the grid, every one at LOD0")
    p.add_argument("--size", default="1920x1080", help="frame size WxH")
    p.add_argument("--rounds", type=int, default=5, help="rounds over the configurations, alternated")
    p.add_argument("--frames", type=int, default=10, help="timed frames per configuration and round (the median of all is reported)")
    p.add_argument("--json", type=Path, help="write the results as JSON to this file")
    p.set_defaults(run=bench_morph)
    p = sub.add_parser("impostor", help="impostor atlas: error against the mesh at the switch distance, bytes and bake time, over a grid of settings")
    p.add_argument("--model", type=Path, help="a .glb/.gltf (default: the built-in zombie)")
    p.add_argument("--distance", type=float, default=60.0, help="metres: the switch distance the impostor is compared at")
    p.add_argument("--quick", action="store_true", help="the default settings only")
    p.add_argument("--far", action="store_true", help="also far impostors (120 to 300 m) against the supersampled mesh, sampled plainly and through mip levels")
    p.add_argument("--json", type=Path, help="write the results as JSON to this file")
    p.set_defaults(run=bench_impostor)
    p = sub.add_parser("ai", help="CPU ms per crowd-AI step against agent count")
    p.add_argument("--model", type=Path, help="a .glb/.gltf (default: the built-in zombie)")
    p.add_argument("--agents", default="200,1000,10000,100000", help='comma-separated agent counts')
    p.add_argument("--steps", type=int, default=600, help='timed AI steps per agent count (the median is reported)')
    p.add_argument("--warmup", type=int, default=120, help='AI steps before timing')
    p.add_argument("--seed", type=int, default=1, help='random seed of the crowd')
    p.add_argument("--think-every", default=None,
                   help="comma-separated think budgets to compare (1: every zombie thinks every substep; default: the setting's); "
                        "the budget applies from the think_from setting's crowd size on")
    p.add_argument("--workers", default=None,
                   help="comma-separated process counts to compare (1: this process only; 0: one per core; default: the setting's)")
    p.add_argument("--town", action="store_true", help="each case twice: on open ground, and in the built-in town (its obstacles)")
    p.add_argument("--path", default="cpu", help="comma-separated AI paths: cpu (numpy), gpu (compute passes, GL 4.3), side by side")
    p.add_argument("--json", type=Path, help='write the results as JSON to this file')
    p.set_defaults(run=bench_ai)
    p = sub.add_parser("ai-agreement", help="the GPU AI against the numpy AI: one substep per agent, and 600 substeps in aggregate")
    p.add_argument("--model", type=Path, help="a .glb/.gltf (default: the built-in zombie)")
    p.add_argument("--agents", type=int, default=1500, help="agents")
    p.add_argument("--seeds", type=int, default=8, help="seeds of the one-substep comparison")
    p.add_argument("--json", type=Path, help="write the results as JSON to this file")
    p.set_defaults(run=bench_agreement)
    p = sub.add_parser("circles", help="FLAME GPU 2's circles workload on this project's GPU grid: ms a step, and whether two runs agree bit for bit")
    p.add_argument("--agents", type=int, default=1_000_000, help="agents")
    p.add_argument("--steps", type=int, default=200, help="steps a run")
    p.add_argument("--read", type=float, default=204.0, help="neighbours read an agent a step (sets the density)")
    p.add_argument("--json", type=Path, help="write the results as JSON to this file")
    p.set_defaults(run=bench_circles)
    p = sub.add_parser("frame", help="the whole headless frame: period (frames back to back, one finish) and latency (a finish per frame)")
    p.add_argument("--agents", default="1000,10000,100000,1000000", help="comma-separated agent counts (1,000,000 takes minutes on llvmpipe)")
    p.add_argument("--scene", type=Path, help="a scene file (default: the default scene)")
    p.add_argument("--size", default="1920x1080", help="frame size WxH")
    p.add_argument("--frames", type=int, default=100, help="frames per period measurement")
    p.add_argument("--repeats", type=int, default=3, help="period measurements per agent count (the median is reported)")
    p.add_argument("--warmup", type=int, default=10, help="frames before measuring (shaders compile, buffers grow)")
    p.add_argument("--dt", type=float, default=None,
                   help="simulated seconds a frame (default: the headless loop's 1/30 s, two AI substeps; 1/60 is what a 60 fps window steps)")
    p.add_argument("--ai-path", default="auto", help="comma-separated AI paths to run each count on, side by side (auto, gpu, cpu)")
    p.add_argument("--workers", type=int, default=None,
                   help="processes that step the AI (the workers setting: 1 this process only, 0 one per core; default: the scene's)")
    p.add_argument("--panel", action="store_true",
                   help="each count twice: without, then with the panel and HUD drawn into the frame as the window draws them")
    p.add_argument("--profile", type=int, default=0, metavar="FRAMES",
                   help="after the timed frames, profile this many more with cProfile: each row gets its top functions (ms a frame)")
    p.add_argument("--orbit", type=float, default=0.0, metavar="DEG_PER_FRAME",
                   help="the camera turns about its target by this many degrees each frame, as a following camera moves (0: still)")
    p.add_argument("--json", type=Path, help="write the rows here")
    p.set_defaults(run=bench_frame)
    p = sub.add_parser("lod", help="silhouette IoU of each coarser LOD against LOD0 at its switch distance (float64, CPU)")
    p.add_argument("--model", type=Path, help="a .glb/.gltf (default: the built-in zombie)")
    p.add_argument("--lod-distances", help="D1,D2,D3 (default: the character's own, for LODs made at load; else the settings' default)")
    p.add_argument("--lod-error-px", help="pixels of error where a made LOD starts (default: the lod_error_px setting's)")
    p.add_argument("--size", default="1920x1080", help="frame size WxH the camera draws")
    p.add_argument("--repeats", type=int, default=3, help="times the LODs of a file without them are made, for the median time")
    p.add_argument("--json", type=Path, help='write the results as JSON to this file')
    p.set_defaults(run=bench_lod)
    p = sub.add_parser("simplifiers", help="the LOD simplifier against fast-simplification, pyfqmr and meshoptimizer (those importable)")
    p.add_argument("--model", type=Path, required=True, help="a .glb/.gltf without coarser LODs")
    p.add_argument("--size", default="1920x1080", help="frame size WxH the camera draws")
    p.add_argument("--json", type=Path, help='write the results as JSON to this file')
    p.set_defaults(run=bench_simplifiers)
    p = sub.add_parser("vertex-cache", help="the hand-written triangle order against meshoptimizer's (needs meshoptimizer built)")
    p.add_argument("--model", type=Path, help="a .glb/.gltf (default: the built-in zombie)")
    p.add_argument("--json", type=Path, help='write the results as JSON to this file')
    p.set_defaults(run=bench_vertex_cache)
    p = sub.add_parser("soak", help="the default scene for many frames: resident memory and live GL objects after warm-up, faults")
    p.add_argument("--agents", type=int, default=10000, help="crowd size")
    p.add_argument("--frames", type=int, default=20000, help="frames to run (a fixed 1/30 s step each)")
    p.add_argument("--warmup", type=int, default=1000, help="frames before the first sample (buffers grow, rounds start)")
    p.add_argument("--every", type=int, default=250, help="frames between samples")
    p.add_argument("--size", default="320x180", help="frame size WxH (small: the soak is about growth, not pixels)")
    p.add_argument("--scene", type=Path, help="a scene file (default: the default scene, the game as shipped)")
    p.add_argument("--heap", action="store_true", help="also trace the Python heap after the warm-up (tracemalloc: slower, exact)")
    p.add_argument("--json", type=Path, help="write the samples and figures here")
    p.set_defaults(run=bench_soak)
    p = sub.add_parser("fragment", help="the fragment processor (GL 3.3 / 4.1) against the compute one: its two passes and the fill floor, GPU ms")
    p.add_argument("--agents", default="16384,65536,131072", help='comma-separated agent counts')
    p.add_argument("--repeats", type=int, default=20, help='timed runs of each pass (the median is reported)')
    p.add_argument("--json", type=Path, help='write the results as JSON to this file')
    p.set_defaults(run=bench_fragment)
    p = sub.add_parser("feedback", help="the transform-feedback cull (GL 4.0 to 4.2) against the compute one, its counting and its feedback draws alone, GPU ms")
    p.add_argument("--agents", default="10000,100000,1000000", help='comma-separated agent counts')
    p.add_argument("--repeats", type=int, default=20, help='timed runs per variant (the median is reported)')
    p.add_argument("--floor", type=int, default=0, help="also time one point draw of this many records by kind: with feedback, a geometry shader, plain")
    p.add_argument("--json", type=Path, help='write the results as JSON to this file')
    p.set_defaults(run=bench_feedback)
    p = sub.add_parser("compaction", help="the GPU cull's compacted lists: GPU ms, entries and bytes an agent, lists checked against the numpy cull")
    p.add_argument("--agents", default="10000,100000,1000000", help='comma-separated agent counts')
    p.add_argument("--repeats", type=int, default=40, help='timed runs per agent count (the median is reported)')
    p.add_argument("--check", type=int, default=100000, help='compare the lists with the numpy cull up to this many agents')
    p.add_argument("--json", type=Path, help='write the results as JSON to this file')
    p.set_defaults(run=bench_compaction)
    p = sub.add_parser("readback", help="weapon socket gather, transfer and wait against armed agents; sync vs unsync error")
    p.add_argument("--agents", type=int, default=10000, help='crowd size')
    p.add_argument("--armed", default="0,100,1000,10000", help='comma-separated counts of armed agents')
    p.add_argument("--latency", type=int, default=2, help='frames between gathering a socket and reading it (1 to 3)')
    p.add_argument("--size", default="1920x1080", help='frame size WxH')
    p.add_argument("--frames", type=int, default=120, help='timed frames per armed count')
    p.add_argument("--warmup", type=int, default=30, help='frames before timing')
    p.add_argument("--error-frames", type=int, default=10, help="frames over which the weapon-to-hand error's maximum is taken")
    p.add_argument("--seed", type=int, default=1, help='random seed of the crowd')
    p.add_argument("--json", type=Path, help='write the results as JSON to this file')
    p.set_defaults(run=bench_readback)
    from .error_report import add_parsers
    from .peers import add_parsers as add_peers_parsers
    from .skate_report import add_parsers as add_skate_parsers
    from .storage_cost import add_parsers as add_storage_cost_parsers
    from .rounds_report import add_parsers as add_rounds_parsers
    from .texture_report import add_parsers as add_texture_parsers
    from .meshopt_decode import add_parsers as add_meshopt_parsers

    add_parsers(sub)
    add_rounds_parsers(sub)
    add_skate_parsers(sub)
    add_storage_cost_parsers(sub)
    add_texture_parsers(sub)
    add_peers_parsers(sub)
    add_meshopt_parsers(sub)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from crowd.sim.config import AIError
    from crowd.anim.bake import BakeError
    from crowd.gl import GLUnavailable
    from crowd.asset.gltf.reader import GltfImportError
    from crowd.pipeline_config import PipelineError
    from crowd.anim.processor_inputs import ProcessorError
    from crowd.draw.readback import ReadbackError
    from crowd.draw.weapons import WeaponError
    from crowd.frame import FrameError
    from crowd.scene import SceneError
    from crowd.settings import SettingError

    from .soak import SoakError

    try:
        return args.run(args)
    except (GltfImportError, BakeError, GLUnavailable, PipelineError, ProcessorError, AIError, ReadbackError, WeaponError,
            FrameError, SettingError, SceneError, SoakError) as exc:
        print(f"crowd-bench: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
