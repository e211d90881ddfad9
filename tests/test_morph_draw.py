"""Morphed and skinned vertices (issue 23, point 3): what the skinned draw's vertex shader computes with
an agent's morph pairs, captured with transform feedback, against the float64 evaluation of glTF's
formula (the bind position plus the weighted deltas, then skinning), with each vertex's bound from the
quantisation of the deltas, the weights and the heading."""

from __future__ import annotations

import numpy as np
import pytest

from crowd.anim.morph import active_pairs, reference_weights
from crowd.anim.processor import AnimationProcessor
from crowd.anim.palette_reference import reference_palette
from crowd.draw.morph import NORMAL_RANGE, SNORM, pack_deltas, position_step, unpack_deltas
from crowd.draw.cull_lists import entry_agents
from crowd.draw.packing import WEIGHT_STEP
from crowd.draw.render import CrowdRenderer
from crowd.frame import Camera, Instances
from test_morph_processor import _baked, _character, _layers
from test_render import capture

AGENTS = 40


def test_packed_deltas_decode_within_half_a_step():
    rng = np.random.default_rng(1)
    p = rng.normal(0.0, 0.03, (500, 3))
    n = rng.uniform(-2.0, 2.0, (500, 3))
    step = float(np.max(np.abs(p))) / SNORM
    dp, dn = unpack_deltas(pack_deltas(p, n, step), step)
    assert np.max(np.abs(dp - p)) <= 0.5 * step + 1e-15
    assert np.max(np.abs(dn - n)) <= 0.5 * NORMAL_RANGE / SNORM + 1e-15


def _capture(ctx, renderer, index, proc):
    """v_world and v_normal of every vertex of every instance of draw `index`, through the MORPH program."""
    def morphs(prog):
        renderer.morph.bind(prog)
        prog["u_morph_vertex_base"] = renderer.draws[index].morph_base

    return capture(ctx, renderer, index, proc, {"MORPH": 1, **({"MORPH_BUFFERS": 1} if renderer.morph_buffers else {})}, setup=morphs)


@pytest.mark.parametrize("path, buffers", [("compute", True), ("compute", False), ("fragment", False)])
def test_morphed_skinned_vertices_match_float64(gl_context, tmp_path, path, buffers):
    """The deltas in storage buffers (GL 4.3) and in textures (the GL 3.3 path's) alike."""
    from crowd.gl import has_compute

    if path == "compute" and not has_compute(gl_context):
        pytest.skip("no GL 4.3")
    ctx = gl_context
    character = _character(tmp_path)
    baked = _baked(character, {"t0": (0.2, 0.6), "t4": (0.0, 0.5)})
    layers = _layers(AGENTS, len(baked.clips))
    rng = np.random.default_rng(9)
    positions = np.column_stack([rng.uniform(-10, 10, AGENTS), np.zeros(AGENTS), rng.uniform(-10, 10, AGENTS)]) + [3e4, 0.0, -1e4]
    yaw = rng.uniform(-np.pi, np.pi, AGENTS).astype(np.float32)
    scale = rng.uniform(0.8, 1.25, AGENTS).astype(np.float32)
    instances = Instances(positions, yaw, scale, np.full((AGENTS, 4), 255, np.uint8))
    camera = Camera(eye=positions.mean(axis=0) + [0.0, 10.0, 30.0], target=positions.mean(axis=0))
    (mesh,) = character.meshes
    with AnimationProcessor(ctx, baked, 4, path=path) as proc, \
            CrowdRenderer(ctx, character, lod_distances=(1e6, 2e6, 3e6), shadows=False, culling=False, morphs=[True],
                              morph_buffers=buffers) as renderer:
        proc.resize(AGENTS)
        proc.process(layers)
        renderer.prepare(camera, instances, palette=proc.layout)
        (draw,) = renderer.draws
        assert draw.morph and renderer.morph is not None and renderer.gpu_bytes()["morphs"] > 0
        world, normal = _capture(ctx, renderer, 0, proc)
        agents = entry_agents(renderer.listed(0))[0]
        gpu_pairs = proc.read_morph_pairs()
    palette = reference_palette(baked, layers)
    pairs = active_pairs(reference_weights(baked.morphs, baked, layers))
    step = position_step([mesh])
    w_skin = mesh.weights.astype(np.float64) / mesh.weights.sum(axis=1, keepdims=True)
    worst, moved = 0.0, 0
    for k, a in enumerate(agents):
        weights = np.zeros(len(character.morphs))
        listed = pairs[a, :, 1] != 0  # the list ends with (0, 0) pairs
        weights[pairs[a, listed, 0].astype(int)] = pairs[a, listed, 1]
        delta_p = np.einsum("t,tvc->vc", weights, mesh.morph_positions.astype(np.float64))
        delta_n = np.einsum("t,tvc->vc", weights, mesh.morph_normals.astype(np.float64))
        base = mesh.positions.astype(np.float64) + delta_p
        n_bind = mesh.normals.astype(np.float64) + delta_n
        m = palette[a][mesh.joints]
        p = np.concatenate([base, np.ones((len(base), 1))], axis=1)
        per_bone = np.einsum("vbij,vj->vbi", m, p)
        skinned = np.einsum("vb,vbi->vi", w_skin, per_bone)
        n = np.einsum("vb,vbij,vj->vi", w_skin, m[..., :3], n_bind)
        c, s = np.cos(float(yaw[a])), np.sin(float(yaw[a]))
        rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        expect = positions[a] - camera.eye + float(scale[a]) * skinned @ rot.T
        # Per vertex: the skinning bound of tests/test_render.py, plus each active target's deltas within
        # half a step a component (times its weight), plus the pairs' float32 weights.
        spread = np.linalg.norm(per_bone - per_bone[:, :1], axis=2)
        total_w = float(np.sum(np.abs(pairs[a, :, 1])))
        morph_bound = total_w * 0.5 * step * np.sqrt(3.0) + 1e-6 * np.linalg.norm(delta_p, axis=1)
        bound = (0.5 * WEIGHT_STEP * spread.sum(axis=1) + 1.5 / 32767 * np.linalg.norm(skinned, axis=1) + morph_bound) * scale[a] + 2e-5
        err = np.linalg.norm(world[k] - expect, axis=1)
        assert np.all(err <= bound), f"agent {a}: {err.max() * 1e3:.4f} mm over a bound of {bound[np.argmax(err)] * 1e3:.4f} mm"
        cos_angle = np.sum(normal[k] * (n @ rot.T), axis=1) / np.linalg.norm(normal[k], axis=1) / np.linalg.norm(n, axis=1)
        assert np.degrees(np.arccos(np.clip(cos_angle.min(), -1, 1))) < 0.5
        worst = max(worst, float(err.max()))
        moved += int(np.count_nonzero(np.linalg.norm(delta_p, axis=1) > 1e-3))
    assert moved > AGENTS  # the targets moved vertices by more than a millimetre in many agents
    assert np.count_nonzero(gpu_pairs[..., 1]) > AGENTS
    print(f"max morphed vertex error {worst * 1e3:.4f} mm")


def _frames(p, target, dt, n):
    for _ in range(n):
        p.frame(target.framebuffer, dt)
    return target.image().astype(int)


@pytest.mark.parametrize("cull", ["gpu", "cpu"])
def test_the_pipeline_draws_morphs_only_where_the_scene_moves_them(gl_context, cull):
    """The built-in zombies, every one fully swollen: the morph bake, the pairs and the deltas exist and
    change the picture; switched off, none of it exists, and on again the same picture comes back (the
    foot lock is off: a new processor starts its planted feet anew); the two cull paths draw the same."""
    from crowd.gl import Offscreen, has_compute
    from crowd.pipeline import CrowdPipeline
    from crowd.pipeline_config import CharacterSpec, PipelineConfig

    if cull == "gpu" and not has_compute(gl_context):
        pytest.skip("no GL 4.3 here")
    size = (320, 180)
    cast = (CharacterSpec("zombie", morph={"belly_swell": (1.0, 1.0)}),)
    config = PipelineConfig(agents=30, seed=3, characters=cast, cull=cull, weapons=False, foot_lock=False)
    with Offscreen(gl_context, size) as target, CrowdPipeline(gl_context, config) as p:
        p.camera = p.overview_camera(size[0] / size[1])
        _frames(p, target, 1 / 30, 6)
        swollen = _frames(p, target, 0.0, 3)
        assert "morph_weights" in p.passes_run
        assert p.processor.gpu_bytes()["morphs"] > 0 and p.renderer.gpu_bytes()["morphs"] > 0
        pairs = p.processor.read_morph_pairs()
        assert np.all(pairs[:, 0, 0] == 1) and np.allclose(np.abs(pairs[:, 0, 1]), 1.0, atol=1e-6)  # belly_swell at 1 leads every list
        p.set("morphs", False)
        p.passes_run.clear()
        plain = _frames(p, target, 0.0, 3)
        assert "morph_weights" not in p.passes_run
        assert p.processor.gpu_bytes()["morphs"] == 0 and p.renderer.gpu_bytes()["morphs"] == 0
        assert p.processor.layout.parts[0].slots == 0 and not any(d.morph for d in p.renderer.draws)
        changed = np.count_nonzero(np.abs(swollen - plain).max(axis=2) > 24)
        assert changed > 30, changed  # the bellies show (30 zombies of about 20 px by 60 at this size)
        p.set("morphs", True)
        again = _frames(p, target, 0.0, 3)
        assert np.count_nonzero(np.abs(again - swollen).max(axis=2) > 24) <= 3
    if cull == "gpu":  # the same frame through the cpu path's draws (a draw per mesh, the table's base per draw)
        config = PipelineConfig(agents=30, seed=3, characters=cast, cull="cpu", weapons=False, foot_lock=False)
        with Offscreen(gl_context, size) as target, CrowdPipeline(gl_context, config) as p:
            p.camera = p.overview_camera(size[0] / size[1])
            _frames(p, target, 1 / 30, 6)
            cpu = _frames(p, target, 0.0, 3)
        assert np.count_nonzero(np.abs(cpu - swollen).max(axis=2) > 24) <= 10


def test_agents_moving_no_target_are_drawn_by_the_plain_twins(gl_context, tmp_path):
    """The GPU cull reads each agent's first morph pair: an agent whose weights move nothing is listed in
    the plain twin of each morph draw (the same geometry, no morph code), the others in the morph draws,
    in the colour and the shadow lists alike; the picture is the one every agent in the morph draws gives."""
    from crowd.frame import CLIP, WEIGHT
    from crowd.gl import Offscreen, has_compute

    if not has_compute(gl_context):
        pytest.skip("no GL 4.3 here")
    ctx = gl_context
    character = _character(tmp_path)
    character = character.__class__(**{**character.__dict__, "morph_defaults": np.zeros(len(character.morphs))})
    baked = _baked(character)
    still_clip = [c.name for c in baked.clips].index("still")
    layers = _layers(AGENTS, len(baked.clips))
    layers[: AGENTS // 2, :, CLIP] = still_clip  # half the crowd plays only the clip that keys no weight
    layers[AGENTS // 2:, 0, CLIP] = 1 - still_clip
    layers[AGENTS // 2:, 0, WEIGHT] = 1.0
    pairs = active_pairs(reference_weights(baked.morphs, baked, layers))
    still = set(np.flatnonzero(pairs[:, 0, 1] == 0).tolist())
    assert 0 < len(still) < AGENTS
    rng = np.random.default_rng(4)
    positions = np.column_stack([rng.uniform(-6, 6, AGENTS), np.zeros(AGENTS), rng.uniform(-6, 6, AGENTS)])
    instances = Instances(positions, rng.uniform(-np.pi, np.pi, AGENTS).astype(np.float32), np.ones(AGENTS, np.float32),
                          np.full((AGENTS, 4), 200, np.uint8))
    camera = Camera(eye=np.array([0.0, 8.0, 20.0]), target=np.zeros(3), aspect=16 / 9)
    pictures = {}
    with AnimationProcessor(ctx, baked, 4) as proc, Offscreen(ctx, (320, 180)) as target, \
            CrowdRenderer(ctx, character, lod_distances=(1e6, 2e6, 3e6), shadows=True, culling=False, cull_path="gpu", morphs=[True]) as renderer:
        proc.resize(AGENTS)
        proc.process(layers)
        morph, twin = renderer.draws[1], renderer.draws[0]
        assert morph.morph and twin.twin_of is morph and not twin.morph
        # GL forbids a sampler2D and a sampler2DArray on one unit; NVIDIA then fetched zeros, routing every agent.
        cull = renderer.gpu.program
        assert cull["u_hiz"].value != cull["u_palette0"].value
        for routed in (True, False):
            view = renderer.prepare(camera, instances, palette=proc.layout, processor=proc if routed else None)
            renderer.refresh_counts(wait=True)
            for cascade in [None, *range(len(twin.shadow_counts))]:
                listed = [set(entry_agents(renderer.listed(d, cascade))[0].tolist()) for d in (0, 1)]
                want = (still, set(range(AGENTS)) - still) if routed else (set(), set(range(AGENTS)))
                assert tuple(listed) == want, (routed, cascade)
            target.framebuffer.use()
            target.framebuffer.clear(0.1, 0.1, 0.1, 1.0, depth=1.0)
            renderer.shadow_pass(view, proc)
            renderer.color_pass(target.framebuffer, view, proc)
            pictures[routed] = target.image().astype(int)
    assert np.count_nonzero(pictures[True] != pictures[False]) <= 8 and np.count_nonzero(np.abs(pictures[True] - 26) > 4) > 500
