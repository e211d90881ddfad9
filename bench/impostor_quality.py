"""crowd-bench impostor: the impostor atlas's error against the atlas's bytes and bake time (issue 24, point 4).

For each atlas setting of a grid (views around the up axis, elevations, cell size), the built-in zombie's
scene clips are baked (timed), and one agent is drawn at the switch distance as the mesh the renderer
draws there and as its impostor, alone, at the demo's pixel density (1080 rows over its field of view,
a 320 x 320 crop), for every clip, at a phase between baked frames, at headings between baked views
and at two camera elevations. Per (clip, heading, elevation) cell: the silhouette IoU, the mean colour
difference over the pixels both cover (0-255), and the median depth difference (metres). Reported per
setting: the atlas's MB and bake seconds, and the worst and mean of each measure; the defaults are chosen
from this trade-off as `crowd-bench error` chose the bake's.
"""

from __future__ import annotations

import itertools
import json
import math
import time
from pathlib import Path

import numpy as np

GRID_VIEWS = (8, 12, 16)
GRID_ELEVATIONS = ((15.0,), (10.0, 40.0))
GRID_CELLS = ((32, 64), (40, 80), (48, 96))
GRID_RATES = (10.0, 20.0)
HEADINGS = 6  # per clip: spread over the circle, each between two baked views of any grid setting
CAMERA_ELEVATIONS = (12.0, 35.0)


class OneAgent:
    """One agent drawn alone at the demo's pixel density (1080 rows over its field of view, a `size`
    square crop), as the mesh or as its impostor: the processor and the two renderers made once, so a
    sweep draws many poses, headings and views without compiling anything again."""

    def __init__(self, ctx, character, baked, atlas, distance: float, size: int = 320, rows: int = 1080):
        from crowd.anim.processor import AnimationProcessor
        from crowd.draw.render import CrowdRenderer
        from crowd.gl import GLObjects, Offscreen

        self.ctx, self.character, self.distance, self.size, self.rows = ctx, character, distance, size, rows
        self._objects = GLObjects()
        try:
            self.proc = self._objects.add(AnimationProcessor(ctx, baked, 4, impostor_keys=[True]))
            self.target = self._objects.add(Offscreen(ctx, (size, size)))
            self.renderers = {kind: self._objects.add(CrowdRenderer(ctx, character, shadows=False, culling=False, cull_path="cpu",
                                                                    impostors=[a], impostor_distance=distance * 0.9))
                              for kind, a in (("mesh", None), ("impostor", atlas))}
            # The mesh one LOD finer than the renderer draws at this distance: what a mesh LOD switch changes.
            finer = [d if d < distance else 1e5 * (k + 1) for k, d in enumerate(self.renderers["mesh"].lod_distances)]
            finer[max(k for k, d in enumerate(self.renderers["mesh"].lod_distances) if d < distance)] = 1e4
            self.renderers["finer mesh"] = self._objects.add(CrowdRenderer(ctx, character, lod_distances=tuple(sorted(finer)), shadows=False,
                                                                           culling=False, cull_path="cpu"))
        except BaseException:
            self._objects.release()
            raise
        self.proc.resize(1)

    def draw(self, kind: str, clip: int, phase: float, yaw: float, elevation_deg: float = 12.0, choice: int = 0):
        """(colour (size, size, 3) float64, covered (size, size) bool, depth in metres along the view);
        `choice`: the piece the agent wears in each variation group (the atlas holds the first's)."""
        from crowd.frame import Camera, Instances
        from crowd.frame import CLIP, MASK, PHASE, WEIGHT, empty_layers

        layers = empty_layers(1, 4)
        layers[0, 0, [CLIP, PHASE, WEIGHT, MASK]] = (clip, phase, 1.0, -1.0)
        self.proc.process(layers)
        groups = {m.group for m in self.character.meshes if m.group}
        inst = Instances(np.zeros((1, 3)), np.array([yaw], np.float32), np.ones(1, np.float32), np.full((1, 4), 255, np.uint8),
                         {g: np.full(1, choice, np.int64) for g in groups})
        e, d, size = math.radians(elevation_deg), self.distance, self.size
        eye = np.array([0.0, 0.9 + d * math.sin(e), d * math.cos(e)])
        fov = 2.0 * math.degrees(math.atan(size / self.rows * math.tan(math.radians(Camera.fov_y) / 2.0)))
        camera = Camera(eye=eye, target=np.array([0.0, 0.9, 0.0]), aspect=1.0, fov_y=fov, near=d * 0.5, far=d * 2.0)
        renderer = self.renderers[kind]
        view = renderer.prepare(camera, inst, palette=self.proc.layout)
        fb = self.target.framebuffer
        fb.use()
        fb.clear(0.0, 0.0, 0.0, 1.0, depth=1.0)
        renderer.color_pass(fb, view, self.proc)
        color = self.target.image().astype(np.float64)
        depth = np.frombuffer(fb.read(attachment=-1, components=1, dtype="f4"), np.float32).reshape(size, size)[::-1].astype(np.float64)
        n, f = camera.near, camera.far
        metres = 2.0 * n * f / (f + n - (depth * 2.0 - 1.0) * (f - n))
        return color, depth < 1.0, metres

    def release(self) -> None:
        self._objects.release()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()


def far_aliasing(ctx, character, baked, atlas, distances=(120.0, 200.0, 300.0), frames: int = 32, size: int = 40,
                 supersample: int = 8) -> list[dict]:
    """Far impostors against the truth, sampling the atlas plainly (as the runtime does) and through two
    mip levels built here (cells of a side divisible by 4 stay on whole texels; the atlas is premultiplied by
    coverage and the depth's two channels decode linearly, so both textures average): one agent walking (the atlas's first looping clip, a baked frame and a
    third a step, so a step lands between baked frames) at each distance at the demo's pixel density, a
    `size`-pixel crop, against the mesh drawn at `supersample` times the density and box-filtered down
    (its anti-aliased truth). Per distance and filter: the mean colour error over the crop (0-255, the
    background black on both), and the flicker: the mean of |impostor's change between frames - the
    truth's change|, the shimmer that is not the walk."""
    import moderngl

    loop = next((c for c in range(len(baked.clips)) if atlas.clips[c, 0, 2]), 0)
    steps = int(atlas.clips[loop, 0, 1])
    rows = []
    for distance in distances:
        with OneAgent(ctx, character, baked, atlas, distance, size) as low, \
                OneAgent(ctx, character, baked, atlas, distance, size * supersample, 1080 * supersample) as high:
            textures = [tex for t in low.renderers["impostor"].impostors if t is not None for tex in (t.albedo, t.normal_depth)]
            if any(c % 4 for c in atlas.settings.cell):
                raise ValueError(f"cells of {atlas.settings.cell} pixels do not stay whole through two mip levels")
            for tex in textures:
                tex.build_mipmaps(0, 2)
            truth, drawn = [], {"mipmapped": [], "linear": []}
            for f in range(frames):
                phase = (f * 4.0 / 3.0 / steps) % 1.0
                colour, _, _ = high.draw("mesh", loop, phase, 0.3)
                truth.append(colour.reshape(size, supersample, size, supersample, 3).mean(axis=(1, 3)))
                for mode, minify in (("mipmapped", moderngl.LINEAR_MIPMAP_LINEAR), ("linear", moderngl.LINEAR)):
                    for tex in textures:
                        tex.filter = (minify, moderngl.LINEAR)
                    drawn[mode].append(low.draw("impostor", loop, phase, 0.3)[0])
        truth = np.stack(truth)
        covered = max(int(np.count_nonzero(truth.max(axis=-1) > 0.0)), 1)  # (pixels the truth touches, all frames)
        row = {"distance_m": distance, "agent_pixels_tall": round(1.8 / (2.0 * distance * math.tan(math.radians(22.5))) * 1080, 1)}
        for mode, images in drawn.items():
            images = np.stack(images)
            row[f"{mode}_error"] = round(float(np.abs(images - truth).sum() / 3.0 / covered), 3)
            row[f"{mode}_flicker"] = round(float(np.abs(np.diff(images, axis=0) - np.diff(truth, axis=0)).sum() / 3.0 / covered), 3)
        rows.append(row)
    return rows


def compare(mesh, impostor) -> dict:
    """IoU, mean colour difference over the pixels both cover, median depth difference there."""
    (mc, mcov, md), (ic, icov, idep) = mesh, impostor
    both = mcov & icov
    union = np.count_nonzero(mcov | icov)
    return {"iou": np.count_nonzero(both) / union if union else 1.0,
            "colour": float(np.abs(mc[both] - ic[both]).mean()) if both.any() else 255.0,
            "depth_m": float(np.median(np.abs(md[both] - idep[both]))) if both.any() else math.inf,
            "mesh_pixels": int(np.count_nonzero(mcov))}


def measure(ctx, character, baked, settings, distance: float) -> dict:
    from crowd.draw.impostor_bake import bake_atlas

    t = time.perf_counter()
    atlas = bake_atlas(ctx, character, baked, settings)
    ctx.finish()
    bake_s = time.perf_counter() - t
    cells, others, references = [], [], []
    choices = min((sum(1 for m in character.meshes if m.lod == 0 and m.group == g) for g in {m.group for m in character.meshes if m.group}),
                  default=1)
    with OneAgent(ctx, character, baked, atlas, distance) as scene:
        for clip in range(len(baked.clips)):
            n = int(atlas.clips[clip, 0, 1])
            phase = (0.5 / n) if atlas.clips[clip, 0, 2] else 0.5 / max(n - 1, 1)  # halfway between two baked frames
            for k, elevation in itertools.product(range(HEADINGS), CAMERA_ELEVATIONS):
                yaw = 2.0 * math.pi * (k + 0.37) / HEADINGS  # between baked views for every view count of the grid
                mesh, imp = (scene.draw(kind, clip, phase, yaw, elevation) for kind in ("mesh", "impostor"))
                cells.append({"clip": baked.clips[clip].name, "yaw": round(yaw, 4), "elevation": elevation, **compare(mesh, imp)})
                references.append(compare(mesh, scene.draw("finer mesh", clip, phase, yaw, elevation)))
                if choices > 1:  # an agent wearing another head: its impostor still shows the first's
                    other = scene.draw("mesh", clip, phase, yaw, elevation, choice=1)
                    others.append(compare(other, imp))
    worst_iou = min(cells, key=lambda c: c["iou"])
    worst_colour = max(cells, key=lambda c: c["colour"])
    return {"views": settings.views, "elevations": list(settings.elevations), "cell": list(settings.cell), "rate": settings.rate,
            "atlas_mb": round(atlas.nbytes / 1e6, 2), "bake_s": round(bake_s, 3),
            "iou_min": round(worst_iou["iou"], 4), "iou_mean": round(float(np.mean([c["iou"] for c in cells])), 4),
            "colour_max": round(worst_colour["colour"], 2), "colour_mean": round(float(np.mean([c["colour"] for c in cells])), 2),
            "depth_m_median": round(float(np.median([c["depth_m"] for c in cells])), 4),
            "worst_iou_cell": worst_iou, "worst_colour_cell": worst_colour,
            # The same cells' mesh against the mesh one LOD finer: what a mesh LOD switch already changes there.
            "mesh_lod_switch": {"iou_mean": round(float(np.mean([c["iou"] for c in references])), 4),
                                "iou_min": round(float(np.min([c["iou"] for c in references])), 4),
                                "colour_mean": round(float(np.mean([c["colour"] for c in references])), 2)},
            # The same cells for an agent wearing each group's second choice, against the atlas of the first.
            "other_choice": None if not others else {"iou_mean": round(float(np.mean([c["iou"] for c in others])), 4),
                                                     "colour_mean": round(float(np.mean([c["colour"] for c in others])), 2)}}


def bench_impostor(args) -> int:
    import moderngl

    from crowd.anim.bake import bake
    from crowd.anim.roles import clips_used, match_roles
    from crowd.asset.gltf import load_character
    from crowd.draw.impostors import ImpostorSettings
    from crowd.gl import describe, headless_context
    from crowd.progress import steps

    from .common import device_cpu

    ctx = headless_context()
    info = describe(ctx)
    character = load_character(args.model) if args.model else load_character()
    roles, _ = match_roles(character.clips)
    baked = bake(character.skeleton, [character.clip(c) for c in clips_used(roles)])
    grid = [ImpostorSettings(v, e, c, r) for v, e, c, r in itertools.product(GRID_VIEWS, GRID_ELEVATIONS, GRID_CELLS, GRID_RATES)]
    if args.quick:
        grid = [ImpostorSettings()]
    print(f"{info['gl_renderer']} | {info['gl_version']} | {character.name}, {len(baked.clips)} clips | at {args.distance:g} m, "
          f"{len(baked.clips) * HEADINGS * len(CAMERA_ELEVATIONS)} (clip, heading, elevation) cells a setting")
    print(f"{'views':>5} {'elevations':>12} {'cell':>7} {'fps':>4} {'MB':>7} {'bake s':>7} {'IoU min':>8} {'IoU mean':>9} {'colour max':>11} "
          f"{'colour mean':>12} {'depth m':>8}")
    rows = []
    for settings in steps(grid, desc="impostor", unit="setting"):
        row = measure(ctx, character, baked, settings, args.distance)
        rows.append(row)
        print(f"{row['views']:>5} {','.join(f'{e:g}' for e in row['elevations']):>12} {'x'.join(map(str, row['cell'])):>7} "
              f"{row['rate']:>4g} {row['atlas_mb']:>7.1f} {row['bake_s']:>7.2f} {row['iou_min']:>8.3f} {row['iou_mean']:>9.3f} {row['colour_max']:>11.1f} "
              f"{row['colour_mean']:>12.1f} {row['depth_m_median']:>8.3f}")
        ref = row["mesh_lod_switch"]
        print(f"{'':>5} for scale, the mesh against the mesh one LOD finer, same cells: IoU min {ref['iou_min']:.3f}, "
              f"mean {ref['iou_mean']:.3f}, colour mean {ref['colour_mean']:.1f}")
        if row["other_choice"]:
            print(f"{'':>5} an agent wearing the second choice of each variation group: IoU mean {row['other_choice']['iou_mean']:.3f}, "
                  f"colour mean {row['other_choice']['colour_mean']:.1f}")
    far = []
    if args.far:  # the default atlas only
        from crowd.draw.impostor_bake import bake_atlas

        far = far_aliasing(ctx, character, baked, bake_atlas(ctx, character, baked))
        print("far impostors, a walking agent against the mesh at 8x the density box-filtered (per pixel the truth covers, 0-255):")
        print(f"{'m':>5} {'px tall':>8} {'error, plain':>13} {'error, 2 mips':>14} {'flicker, plain':>15} {'flicker, 2 mips':>16}")
        for r in far:
            print(f"{r['distance_m']:>5g} {r['agent_pixels_tall']:>8.1f} {r['linear_error']:>13.2f} {r['mipmapped_error']:>14.2f} "
                  f"{r['linear_flicker']:>15.2f} {r['mipmapped_flicker']:>16.2f}")
    if args.json:
        from crowd.files import atomic_write_bytes

        device = f"{info['gl_renderer']}, {info['gl_version']}; {device_cpu()}; moderngl {moderngl.__version__}"
        atomic_write_bytes(Path(args.json), json.dumps({"device": device, "distance_m": args.distance, "rows": rows, "far": far,
                                                        "date": time.strftime("%Y-%m-%d")}, indent=1).encode())
    ctx.release()
    return 0
