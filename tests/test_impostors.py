"""Animated impostors (issue 24): the atlas against a float64 rasterisation of the same pose and view,
an impostor against the mesh it replaces (silhouette, colour and depth), the cache rebuilt after
corruption, and the scenes that need no impostors allocating nothing for them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crowd.anim.bake import bake
from crowd.anim.processor import AnimationProcessor
from crowd.anim.palette_reference import reference_palette
from crowd.anim.roles import clips_used, match_roles
from crowd.asset.gltf import load_character
from crowd.draw.impostor_bake import bake_atlas, load_atlas
from crowd.draw.impostors import (ImpostorSettings, _default_meshes, read_atlas, skinned_points,
                                  view_axes)
from crowd.draw.render import CrowdRenderer
from crowd.frame import Camera, Instances
from crowd.frame import CLIP, MASK, PHASE, WEIGHT, empty_layers

SMALL = ImpostorSettings(views=8, elevations=(0.0, 30.0), cell=(40, 80), rate=6.0)


@pytest.fixture(scope="module")
def zombie():
    character = load_character()
    roles, _ = match_roles(character.clips)
    return character, bake(character.skeleton, [character.clip(c) for c in clips_used(roles)])


@pytest.fixture(scope="module")
def atlas(gl_context, zombie):
    return bake_atlas(gl_context, *zombie, SMALL)


def _rasterise(points2d, depth, triangles, size):
    """Coverage and nearest depth of triangles over a grid of texel centres (float64, for the test)."""
    w, h = size
    cover = np.zeros((h, w), bool)
    nearest = np.full((h, w), np.inf)
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    for tri in triangles:
        p = points2d[tri]
        lo, hi = np.floor(p.min(axis=0)).astype(int), np.ceil(p.max(axis=0)).astype(int)
        x0, x1, y0, y1 = max(lo[0], 0), min(hi[0], w), max(lo[1], 0), min(hi[1], h)
        if x0 >= x1 or y0 >= y1:
            continue
        px, py = xs[y0:y1, x0:x1], ys[y0:y1, x0:x1]
        (ax, ay), (bx, by), (cx, cy) = p
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if abs(area) < 1e-12:
            continue
        l1 = ((px - ax) * (cy - ay) - (py - ay) * (cx - ax)) / area
        l2 = ((bx - ax) * (py - ay) - (by - ay) * (px - ax)) / area
        l0 = 1.0 - l1 - l2
        inside = (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
        z = l0 * depth[tri[0]] + l1 * depth[tri[1]] + l2 * depth[tri[2]]
        block = nearest[y0:y1, x0:x1]
        closer = inside & (z < block)
        block[closer] = z[closer]
        cover[y0:y1, x0:x1] |= inside
    return cover, nearest


@pytest.mark.parametrize("clip, phase, column", [(0, 0.0, 0), (1, 0.4, 3), (2, 0.6, 9), (5, 1.0, 13)])
def test_atlas_cells_match_a_float64_rasterisation_of_the_pose(atlas, zombie, clip, phase, column):
    """A cell's coverage against the float64 skinned LOD0 triangles projected into the cell by the same
    view and box: IoU at least 0.96 (only texels the edges cross may differ), and the depth it holds
    within 2 % of the box's depth range (16-bit storage, float32 skinning) where both cover."""
    character, baked = zombie
    s = atlas.settings
    first, count, loop, _ = atlas.clips[clip, 0]
    frame = int(first) + (int(round(phase * count)) % int(count) if loop else int(round(phase * (count - 1))))
    phase = ((frame - first) / count) if loop else (frame - first) / (count - 1)
    layers = empty_layers(1, 1)
    layers[0, 0, [CLIP, PHASE, WEIGHT, MASK]] = (clip, phase, 1.0, -1.0)
    points = skinned_points(character, reference_palette(baked, layers))[0]
    meshes = _default_meshes(character)
    starts = np.cumsum([0] + [len(m.positions) for m in meshes])
    triangles = np.concatenate([m.indices.reshape(-1, 3) + start for m, start in zip(meshes, starts)])
    elevation = s.elevations[column // s.views]
    right, up, toward = view_axes(2.0 * math.pi * (column % s.views) / s.views, math.radians(elevation))
    half, bottom, height, depth_range = atlas.clips[clip, 1].astype(np.float64)
    cw, ch = s.cell
    uv = np.c_[(points @ right / half * 0.5 + 0.5) * cw, (points @ up - bottom) / height * ch]
    cover, nearest = _rasterise(uv, -(points @ toward) / depth_range, triangles, (cw, ch))
    layer, row = divmod(frame, atlas.rows)
    cell = np.s_[layer, row * ch:(row + 1) * ch, column * cw:(column + 1) * cw]
    got = atlas.albedo[cell][..., 3] > 127
    iou = np.count_nonzero(got & cover) / np.count_nonzero(got | cover)
    assert iou >= 0.96, iou
    nd = atlas.normal_depth[cell].astype(np.float64)
    stored = (nd[..., 2] * 256 + nd[..., 3]) / 65535.0 * 2.0 - 1.0  # toward the camera, in depth ranges
    both = got & cover
    assert np.percentile(np.abs(stored[both] + nearest[both]), 95) <= 0.02 * 2


def test_an_impostor_matches_the_mesh_it_replaces(gl_context, zombie):
    """At the default switch distance (60 m, at the demo's pixel density: the agent about 45 pixels
    tall) the default atlas's impostor against the mesh the renderer draws there (LOD2), same pose and
    heading (between baked views): silhouette IoU, mean colour difference over the pixels both cover,
    and the median depth difference there. Measured on llvmpipe: IoU 0.74 (at this size a pixel of
    edge moves it by about 0.1; a mesh LOD step scores about 0.9), colour 25.2 of 255, depth 0.039 m; the
    bounds leave a little room."""
    from bench.impostor_quality import OneAgent, compare

    character, baked = zombie
    atlas = bake_atlas(gl_context, character, baked)
    with OneAgent(gl_context, character, baked, atlas, 60.0) as scene:
        mesh, impostor = (scene.draw(kind, clip=1, phase=0.3, yaw=0.7) for kind in ("mesh", "impostor"))
    got = compare(mesh, impostor)
    iou, colour, depth = got["iou"], got["colour"], got["depth_m"]
    mesh_cover = mesh[1]
    print(f"impostor vs mesh at 60 m: IoU {iou:.3f}, colour {colour:.1f}, depth median {depth:.3f} m, "
          f"{np.count_nonzero(mesh_cover)} mesh pixels")
    assert np.count_nonzero(mesh_cover) > 150
    assert iou >= 0.7 and colour <= 28.0 and depth <= 0.1


def test_the_cache_is_rebuilt_after_corruption(gl_context, zombie, tmp_path, monkeypatch):
    monkeypatch.setenv("CROWD_CACHE_DIR", str(tmp_path))
    character, baked = zombie
    first = load_atlas(gl_context, character, baked, SMALL)
    (path,) = tmp_path.glob("*.npz")
    assert first.notes == [] and read_atlas(path).checksum() == first.checksum()
    again = load_atlas(gl_context, character, baked, SMALL)  # from the cache
    assert again.notes == [] and again.checksum() == first.checksum()
    data = bytearray(path.read_bytes())
    for damage in (lambda d: d[: len(d) // 2], lambda d: d[:-300] + bytes(300), lambda d: b"not a zip at all"):
        path.write_bytes(bytes(damage(data)))
        rebuilt = load_atlas(gl_context, character, baked, SMALL)
        assert len(rebuilt.notes) == 1 and "rebuilt" in rebuilt.notes[0] and "\n" not in rebuilt.notes[0], rebuilt.notes
        assert rebuilt.checksum() == first.checksum()
        assert read_atlas(path).checksum() == first.checksum()  # and written back whole


def test_only_scenes_that_need_impostors_allocate_them(gl_context):
    """auto with 200 agents (meshes fit): no atlas, no keys, no impostor bytes; on with 0 agents and then
    a few, and back: frames run, the pass appears only with the atlas."""
    from crowd.gl import Offscreen
    from crowd.pipeline import CrowdPipeline
    from crowd.pipeline_config import PipelineConfig

    with Offscreen(gl_context, (160, 90)) as target:
        with CrowdPipeline(gl_context, PipelineConfig(agents=200, seed=1, impostors="auto")) as p:
            assert not p.impostors_needed() and all(m.impostor is None for m in p.cast)
            p.frame(target.framebuffer, 1 / 30)
            assert "impostors" not in p.passes_run and p.renderer.gpu_bytes()["impostors"] == 0
            assert not any(part.key for part in p.processor.layout.parts)
        with CrowdPipeline(gl_context, PipelineConfig(agents=0, seed=1, impostors="on", impostor_distance=5.0)) as p:
            p.frame(target.framebuffer, 1 / 30)
            assert p.renderer.gpu_bytes()["impostors"] > 0
            p.set("agents", 30)
            p.camera = p.overview_camera(16 / 9)
            for _ in range(3):
                p.frame(target.framebuffer, 1 / 30)
            assert "impostors" in p.passes_run and p.processor.read_impostor_keys().shape == (30, 4)
            p.set("impostors", "off")
            assert p.renderer.gpu_bytes()["impostors"] == 0 and all(m.impostor is None for m in p.cast)
            p.frame(target.framebuffer, 1 / 30)


@pytest.mark.parametrize("path", ["cpu", "gpu"])
def test_lod_switches_cross_fade_without_a_pop(gl_context, zombie, atlas, path):
    """One agent 30 m away while the switch distance sweeps past it in steps of 1/16 of the band: as its
    impostor (from LOD1) and as LOD2 (from LOD1). With a 2 m band no frame may change more pixels than
    its share of the band allows (each step moves 1/16 of the pixels that differ between the two LODs,
    twice that for the dither's unevenness, and a few); with no band the switch changes them all in one
    frame, which the same bound catches."""
    from crowd.gl import Offscreen, has_compute

    if path == "gpu" and not has_compute(gl_context):
        pytest.skip("no GL 4.3 here")
    character, baked = zombie
    layers = empty_layers(1, 4)
    layers[0, 0, [CLIP, PHASE, WEIGHT, MASK]] = (1, 0.3, 1.0, -1.0)
    inst = Instances(np.zeros((1, 3)), np.array([0.4], np.float32), np.ones(1, np.float32), np.full((1, 4), 255, np.uint8),
                     {"head": np.zeros(1, np.int64)})
    distance, band, steps = 30.0, 2.0, 16
    fov = 2.0 * math.degrees(math.atan(160 / 1080 * math.tan(math.radians(Camera.fov_y) / 2.0)))
    camera = Camera(eye=np.array([0.0, 1.0, distance]), target=np.array([0.0, 0.9, 0.0]), aspect=1.0, fov_y=fov)
    worst = {}
    with AnimationProcessor(gl_context, baked, 4, impostor_keys=[True]) as proc, Offscreen(gl_context, (160, 160)) as target:
        proc.resize(1)
        proc.process(layers)
        for fade in (band, 0.0):
            for switch in ("impostor", "lod2"):
                with CrowdRenderer(gl_context, character, shadows=False, culling=False, cull_path=path, impostors=[atlas],
                                   impostor_distance=1e6, lod_distances=(14.0, 1e5, 2e5), lod_fade=fade) as renderer:
                    frames = []
                    for k in range(-2, steps + 3):  # the switch from just past the agent to a band short of it
                        at = distance + 0.01 - band * k / steps
                        if switch == "impostor":
                            renderer.set_impostor_distance(at)
                        else:
                            renderer.lod_distances = (14.0, at, 2e5)
                        view = renderer.prepare(camera, inst, palette=proc.layout, processor=proc)
                        fb = target.framebuffer
                        fb.use()
                        fb.clear(0.0, 0.0, 0.0, 1.0, depth=1.0)
                        renderer.color_pass(fb, view, proc)
                        frames.append(target.image().astype(np.int32))
                differ = np.count_nonzero(np.abs(frames[0] - frames[-1]).max(axis=2) > 8)
                changes = [np.count_nonzero(np.abs(a - b).max(axis=2) > 8) for a, b in zip(frames, frames[1:])]
                worst[fade, switch] = (max(changes), differ)
    print(worst)
    for switch in ("impostor", "lod2"):
        step_max, differ = worst[band, switch]
        assert differ > 40, (switch, differ)  # the two LODs do differ here
        assert step_max <= 2.0 * differ / steps + 6, (switch, step_max, differ)
        assert worst[0.0, switch][0] > 2.0 * differ / steps + 6  # the bound would catch a pop


@pytest.mark.parametrize("path", ["cpu", "gpu"])
def test_impostors_hold_their_weapons_without_a_read_back(gl_context, path):
    """Every agent past the impostor distance: no socket is gathered for a zombie and no weapon placed
    on the CPU, yet each armed one's impostor holds its own weapon (a held piece on the socket joint,
    drawn from its palette row), and an unarmed one none."""
    from crowd.gl import Offscreen, has_compute
    from crowd.pipeline import CrowdPipeline
    from crowd.pipeline_config import PipelineConfig
    from crowd.draw.impostors import HELD_GROUP

    if path == "gpu" and not has_compute(gl_context):
        pytest.skip("no GL 4.3 here")
    config = PipelineConfig(agents=80, seed=4, impostors="on", impostor_distance=1.0, lod_fade=0.0, cull=path, culling=False)
    with Offscreen(gl_context, (160, 90)) as target, CrowdPipeline(gl_context, config) as p:
        for _ in range(4):
            p.frame(target.framebuffer, 1 / 30)
        p.renderer.refresh_counts(wait=True)
        held = {d.piece: d.count for d in p.renderer.draws if d.piece.startswith(HELD_GROUP + ":")}
        weapon = p.ai.weapon[p.ai.armed()]
        names = list(p.character.props)
        assert sorted(held) == sorted(f"{HELD_GROUP}:{n}" for n in names)
        assert [held[f"{HELD_GROUP}:{n}"] for n in names] == [int(np.count_nonzero(weapon == k)) for k in range(len(names))]
        assert sum(held.values()) > 10
        assert p.weapons.last["drawn"] == 0 and all(v == 0 for v in p._socket_entries.values())
        # The switch inside the crowd: an agent's weapon is placed or held, never both.
        p.camera = p.overview_camera(16 / 9)
        p.set("impostor_distance", float(np.median(np.linalg.norm(p.instances().position - p.camera.eye, axis=1))))
        for _ in range(5):
            p.frame(target.framebuffer, 1 / 30)
        p.renderer.refresh_counts(wait=True)
        held = sum(d.count for d in p.renderer.draws if d.piece.startswith(HELD_GROUP + ":"))
        placed = p.weapons.last["drawn"]
        assert held > 0 and placed > 0 and held + placed <= int(np.count_nonzero(p.ai.armed())), (held, placed)


def test_both_processor_paths_write_the_heaviest_layers_key(gl_context, zombie):
    """The key texel (first of each agent's row): the clip and phase of its heaviest layer, the first of
    equals, (-1, 0) when no layer weighs anything; the joints' matrices the same with and without it."""
    from crowd.gl import has_compute

    character, baked = zombie
    rng = np.random.default_rng(0)
    n = 50
    layers = empty_layers(n, 4)
    layers[..., CLIP] = rng.integers(0, len(baked.clips), (n, 4))
    layers[..., PHASE] = rng.uniform(0.0, 1.0, (n, 4))
    layers[..., WEIGHT] = rng.uniform(0.0, 1.0, (n, 4))
    layers[..., MASK] = -1.0
    layers[0, :, WEIGHT] = 0.0  # the rest pose
    layers[1, :, WEIGHT] = 0.5  # all equal: the first
    heaviest = np.argmax(layers[..., WEIGHT], axis=1)
    want = np.c_[layers[np.arange(n), heaviest, CLIP], layers[np.arange(n), heaviest, PHASE]]
    want[0] = (-1.0, 0.0)
    paths = ["fragment"] + (["compute"] if has_compute(gl_context) else [])
    for path in paths:
        palettes = []
        for keys in (True, False):
            with AnimationProcessor(gl_context, baked, 4, path=path, impostor_keys=[keys]) as proc:
                proc.resize(n)
                proc.process(layers)
                palettes.append(proc.read_palette())
                if keys:
                    got = proc.read_impostor_keys()
                    assert proc.layout.parts[0].key and got.shape == (n, 4)
                    assert np.array_equal(got[:, :2], want.astype(np.float32)), path
                else:
                    assert proc.read_impostor_keys().shape == (n, 0)
        assert np.array_equal(palettes[0], palettes[1]), path


def test_far_impostors_are_measured_against_the_supersampled_mesh(gl_context, zombie, atlas):
    """crowd-bench impostor --far: the error and the flicker per pixel the truth covers, both ways of sampling."""
    from bench.impostor_quality import far_aliasing

    (row,) = far_aliasing(gl_context, *zombie, atlas, distances=(150.0,), frames=4, size=24, supersample=4)
    assert row["agent_pixels_tall"] == pytest.approx(15.6, abs=0.1)
    for key in ("mipmapped_error", "linear_error", "mipmapped_flicker", "linear_flicker"):
        assert 0.0 < row[key] < 128.0  # (measured, and within the 0-255 scale's lower half)


def test_auto_makes_impostors_by_the_triangles_the_far_meshes_would_draw(zombie):
    """"auto": the built-ins get impostors from 5,000 agents; a character whose coarsest LOD draws 5 times
    the triangles gets them from a fifth of that; a spread too small for the impostor distance gets none."""
    import dataclasses
    from types import SimpleNamespace

    from crowd.live_settings import IMPOSTOR_TRIANGLES, LiveSettings, far_triangles
    from crowd.pipeline_config import PipelineConfig

    character = zombie[0]
    assert far_triangles(character, 3) == 138 and far_triangles(character, 1) == 996 + 160 + 196
    far = max(m.lod for m in character.meshes if m.lod <= 3)
    heavy = dataclasses.replace(character, meshes=[m for m in character.meshes if m.lod != far] + [
        dataclasses.replace(m, indices=np.tile(m.indices, 5)) for m in character.meshes if m.lod == far])
    assert far_triangles(heavy, 3) == 5 * 138

    def needed(member, agents, half_extent=400.0):
        fake = SimpleNamespace(config=PipelineConfig(impostors="auto"), cast=[SimpleNamespace(character=member)], crowd_cast=1,
                               counts=(agents, 1), ai=SimpleNamespace(n=agents, half_extent=half_extent))
        return LiveSettings.impostors_needed(fake)

    assert IMPOSTOR_TRIANGLES == 5_000 * 138
    assert not needed(character, 4_999) and needed(character, 5_000)
    assert not needed(heavy, 999) and needed(heavy, 1_000)
    assert not needed(heavy, 100_000, half_extent=1.0)


def test_small_impostors_show_their_nearest_cell_at_the_blends_error(gl_context, zombie, atlas, monkeypatch):
    """An impostor shorter than BLEND_PX on screen skips the blend of four cells (two views by two frames)
    for its nearest cell: at 150 m (15.6 pixels tall) the picture changes, and its error and flicker against
    the supersampled mesh stay near the blend's (crowd-bench impostor --far measures both)."""
    import crowd.draw.impostors as impostors
    from bench.impostor_quality import far_aliasing

    assert impostors.BLEND_PX > 15.6
    (nearest,) = far_aliasing(gl_context, *zombie, atlas, distances=(150.0,), frames=4, size=24, supersample=4)
    monkeypatch.setattr(impostors, "BLEND_PX", 0.0)
    (blended,) = far_aliasing(gl_context, *zombie, atlas, distances=(150.0,), frames=4, size=24, supersample=4)
    print(f"150 m: nearest cell {nearest}, four cells blended {blended}")
    assert nearest["linear_error"] != blended["linear_error"]  # the nearest cell was drawn
    assert nearest["linear_error"] <= 1.25 * blended["linear_error"] + 1.0
    assert nearest["linear_flicker"] <= 1.5 * blended["linear_flicker"] + 1.0


def test_each_cell_is_drawn_over_its_covered_rectangle_alone(gl_context, atlas, monkeypatch):
    """The quad spans the covered texels of the cells it shows, with a texel of margin (the rest of the
    clip's box is empty): every covered texel lies inside its cell's rectangle, the rectangles are a
    fraction of the box, and the crowd's picture is the one full boxes draw, to rounding."""
    from crowd.draw import impostors
    from crowd.gl import Offscreen
    from crowd.pipeline import CrowdPipeline
    from crowd.pipeline_config import PipelineConfig

    bounds = atlas.cell_bounds()
    cw, ch = atlas.settings.cell
    layers, height, width, _ = atlas.albedo.shape
    cover = atlas.albedo[..., 3].reshape(layers * (height // ch), ch, width // cw, cw).transpose(0, 2, 1, 3)[: atlas.frames]
    frame, column, y, x = np.nonzero(cover)
    u, v = (x + 0.5) / cw, (y + 0.5) / ch
    b = bounds[frame, column]
    assert np.all((b[:, 0] < u) & (u < b[:, 2]) & (b[:, 1] < v) & (v < b[:, 3]))
    share = float(np.mean((bounds[..., 2] - bounds[..., 0]) * (bounds[..., 3] - bounds[..., 1])))
    assert 0.1 < share < 0.8, share

    def picture(full: bool):
        if full:
            tight = impostors.ImpostorAtlas.cell_bounds
            monkeypatch.setattr(impostors.ImpostorAtlas, "cell_bounds",
                                lambda self: np.tile(np.array([0.0, 0.0, 1.0, 1.0], np.float32), tight(self).shape[:2] + (1,)))
        size = (240, 135)
        with Offscreen(gl_context, size) as target, CrowdPipeline(gl_context, PipelineConfig(agents=600, seed=2, impostors="on", weapons=False)) as p:
            p.camera = p.default_camera(size[0] / size[1])
            p.renderer.set_impostor_distance(4.0)
            for _ in range(3):
                p.frame(target.framebuffer, 1 / 30)
            p.refresh_counts()
            assert p.renderer.last["impostors"] > 100
            return target.image().astype(int)

    tight, full = picture(False), picture(True)
    differ = np.abs(tight - full).max(axis=-1)
    assert np.count_nonzero(differ > 8) <= 2 and np.count_nonzero(differ) <= 0.01 * differ.size
