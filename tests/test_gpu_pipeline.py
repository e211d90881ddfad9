"""The crowd on the GPU in the whole frame (the ai_path setting, crowd.gpu_crowd), on llvmpipe: the same
crowd and picture as the numpy AI's, the survivor's rounds through the read-back facts, a person's
overrides, a resize, the bytes a frame sends, and where it refuses to run."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from crowd.frame import ForcedClip, LayerOverrides
from crowd.gl import Offscreen
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import PipelineConfig, PipelineError
from crowd.sim.config import AIConfig

SIZE = (160, 90)
UNARMED = dict(weapons=False, ai=AIConfig(think_every=1, start_clear=0.0))


def run(ctx, config, frames=40, dt=1 / 30, overrides=None):
    with Offscreen(ctx, SIZE) as target, CrowdPipeline(ctx, config) as p:
        p.camera = p.overview_camera(SIZE[0] / SIZE[1])
        for _ in range(frames):
            p.frame(target.framebuffer, dt, overrides)
        image = target.image()
        p.refresh_counts()
        ai = p.ai if p.gpu_crowd is None else p.gpu_crowd.store()
        state = {k: getattr(ai, k).copy() for k in ("x", "z", "state", "phase")}
        return p.ai_path, image, state, dict(p.frame_bytes()), list(p.passes_run), p.renderer.last["visible"], p.survivor


@pytest.fixture
def ctx(compute_context):
    return compute_context


def test_the_gpu_crowd_draws_what_the_numpy_crowd_draws(ctx):
    cpu = run(ctx, PipelineConfig(agents=400, seed=4, ai_path="cpu", **UNARMED))
    gpu = run(ctx, PipelineConfig(agents=400, seed=4, ai_path="gpu", **UNARMED))
    assert cpu[0] == "cpu" and gpu[0] == "gpu"
    a, b = cpu[2], gpu[2]
    assert np.count_nonzero(a["state"] != b["state"]) <= 4  # (agents at a threshold may differ by a substep)
    assert np.percentile(np.hypot(a["x"] - b["x"], a["z"] - b["z"]), 95) < 0.01
    assert abs(cpu[5] - gpu[5]) <= 4
    assert np.mean(np.abs(cpu[1].astype(int) - gpu[1].astype(int))) < 1.0  # the same picture, to a few pixels' edges
    # Nothing per agent crosses in a frame: a few counters back, a few writes in.
    assert gpu[3]["upload_bytes"] <= 64 * 1024 and gpu[3]["readback_bytes"] <= 256
    assert cpu[3]["upload_bytes"] >= 400 * 96


def test_the_survivor_plays_its_rounds_through_the_read_back(ctx):
    config = PipelineConfig(agents=300, seed=2, survivor=True, ai_path="gpu", weapons=False,
                            ai=AIConfig(think_every=1, start_clear=3.0, notice_radius=30.0, forget_radius=40.0, half_extent=12.0, health=1))
    path, _, _, sent, passes, _, survivor = run(ctx, config, frames=150)
    assert path == "gpu" and "process" in passes
    rounds = survivor.history + [survivor.round_record()]
    assert sum(r["blows"] for r in rounds) > 0  # the zombies' blows came back and hurt it
    assert all(r["length_s"] > 1.0 for r in survivor.history), rounds  # (no round ends on the last crowd's blows)
    assert sum(r["kills"] for r in rounds) > 0  # its swings' kills came back
    assert sent["upload_bytes"] <= 64 * 1024


def test_overrides_play_on_the_gpu_as_on_the_cpu(ctx):
    forced = LayerOverrides(ForcedClip(2, 0.0, np.array([3, 5, 7])), {1: (0.25, None), 2: (0.5, np.array([5]))})
    everyone = LayerOverrides(ForcedClip(1, 0.0), {3: (0.0, None)})
    for overrides in (forced, everyone):
        layers = {}
        for path in ("cpu", "gpu"):
            with Offscreen(ctx, SIZE) as target, CrowdPipeline(ctx, PipelineConfig(agents=50, seed=1, ai_path=path, **UNARMED)) as p:
                p.frame(target.framebuffer, 1 / 30, overrides)
                layers[path] = p.processor.read_layers()[:50]
        assert np.abs(layers["cpu"] - layers["gpu"]).max() < 1e-3


def test_a_resize_keeps_the_crowd_on_the_gpu(ctx):
    with Offscreen(ctx, SIZE) as target, CrowdPipeline(ctx, PipelineConfig(agents=0, ai_path="gpu", **UNARMED)) as p:
        p.frame(target.framebuffer, 1 / 30)
        for n in (100_000, 40, 0, 7):
            p.set("agents", n)
            p.frame(target.framebuffer, 1 / 30)
            assert p.ai_path == "gpu" and p.gpu_crowd.gpu.n == n
        kept = p.gpu_crowd.store().tint.copy()
        p.set("agents", 20)
        p.frame(target.framebuffer, 1 / 30)
        assert np.array_equal(p.gpu_crowd.store().tint[:7], kept)


def test_auto_falls_back_where_the_gpu_ai_cannot_run_and_gpu_refuses_in_one_line(ctx):
    with CrowdPipeline(ctx, PipelineConfig(agents=20, ai_path="auto")) as p:  # weapons on: on the GPU too
        assert p.ai_path == "gpu" and p.ai_note is None
    with CrowdPipeline(ctx, PipelineConfig(agents=20, ai_path="auto", cull="cpu")) as p:
        assert p.ai_path == "cpu" and "cull" in p.ai_note
    with CrowdPipeline(ctx, PipelineConfig(agents=20, ai_path="auto", town=True)) as p:  # the town: on the GPU too
        assert p.ai_path == "gpu"
    with pytest.raises(PipelineError, match="^ai_path gpu: .*cull") as refused:
        CrowdPipeline(ctx, PipelineConfig(agents=20, ai_path="gpu", cull="cpu", weapons=False))
    assert "\n" not in str(refused.value)


def test_a_live_change_it_cannot_run_with_moves_the_crowd_to_the_numpy_ai(ctx):
    with Offscreen(ctx, SIZE) as target, CrowdPipeline(ctx, PipelineConfig(agents=200, ai_path="gpu", **UNARMED)) as p:
        for _ in range(5):
            p.frame(target.framebuffer, 1 / 30)
        before = p.gpu_crowd.store().x.copy()
        p.set("cull", "cpu")
        p.frame(target.framebuffer, 1 / 30)
        assert p.ai_path == "cpu" and "moved to the numpy AI" in p.ai_note
        assert np.abs(p.ai.x - before).max() < 1.0  # the same crowd, a frame on


def test_the_session_sees_a_gpu_crowd_through_its_facts(ctx):
    from crowd.scene import Scene
    from crowd.session import CrowdSession

    scene = Scene(agents=120, town=False, weapons=False, ai_path="gpu", ai=AIConfig(think_every=1, start_clear=2.0, half_extent=10.0))
    with CrowdSession(ctx, scene, 16 / 9) as session, Offscreen(ctx, SIZE) as target:
        p = session.pipeline
        assert p.ai_path == "gpu"
        session.selected = 7
        for _ in range(6):
            p.frame(target.framebuffer, 1 / 30)
        row = session.inspect()
        truth = p.gpu_crowd.store()
        assert row is not None and row["agent"] == 7
        assert np.hypot(row["position"][0] - truth.x[7], row["position"][1] - truth.z[7]) < 0.5  # N frames late
        hud = session.hud()
        assert hud is not None and hud["near"] > 0
        counts = p.crowd_ai.counts()
        assert sum(counts.values()) == 120
        assert len(session.markers()[0]) == 2  # the player and the selected agent


def test_the_gpu_crowd_leaves_no_gl_object_on_any_path(ctx, monkeypatch):
    from conftest import gl_census

    before = gl_census()
    with Offscreen(ctx, SIZE) as target, CrowdPipeline(ctx, PipelineConfig(agents=300, ai_path="gpu", **UNARMED)) as p:
        for n in (0, 5000, 0, 300):
            p.set("agents", n)
            p.frame(target.framebuffer, 1 / 30)
        p.set("shadows", False)  # a new renderer: told again to pack records on the GPU
        p.frame(target.framebuffer, 1 / 30)
        assert p.renderer.gpu_record_pass is not None
    assert gl_census() == before
    from crowd.sim.gpu.ai import GpuCrowdAI

    monkeypatch.setattr(GpuCrowdAI, "write_layers", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("injected")))
    with pytest.raises(RuntimeError, match="injected"):
        with Offscreen(ctx, SIZE) as target, CrowdPipeline(ctx, PipelineConfig(agents=100, ai_path="gpu", **UNARMED)) as p:
            p.frame(target.framebuffer, 1 / 30)
    assert gl_census() == before


def test_weapons_stay_in_the_hand_on_the_gpu_path(ctx):
    """The sockets come back from the GPU's own list of armed agents: the same weapons placed as the numpy
    path places, in the hand to the bit (the body drawn with the read-back's palette)."""
    placed = {}
    for path in ("cpu", "gpu"):
        config = PipelineConfig(agents=300, seed=6, ai_path=path, survivor=True, ai=AIConfig(think_every=1, start_clear=0.0))
        with Offscreen(ctx, SIZE) as target, CrowdPipeline(ctx, config) as p:
            p.camera = p.default_camera(SIZE[0] / SIZE[1])
            for _ in range(30):
                p.frame(target.framebuffer, 1 / 30)
            p.refresh_counts()
            assert p.ai_path == path
            placed[path] = dict(p.weapons.last)
            assert p.weapon_error_mm() < 1e-3
            if path == "gpu":
                assert p.frame_bytes()["upload_bytes"] <= 64 * 1024
    assert placed["cpu"]["weapons"] == placed["gpu"]["weapons"] > 0
    assert abs(placed["cpu"]["drawn"] - placed["gpu"]["drawn"]) <= 2


def test_picking_finds_the_agent_the_numpy_pick_finds(ctx):
    from crowd.scene import Scene
    from crowd.session import CrowdSession

    size = (320, 180)
    picks = {}
    for path in ("cpu", "gpu"):
        scene = Scene(agents=200, seed=3, town=False, weapons=False, ai_path=path, ai=AIConfig(think_every=1, start_clear=0.0, half_extent=12.0))
        with CrowdSession(ctx, scene, size[0] / size[1]) as session, Offscreen(ctx, size) as target:
            session.pipeline.frame(target.framebuffer, 1 / 30)
            picks[path] = []
            for x in range(20, 320, 37):
                for y in range(30, 180, 29):
                    answer, waited = session.pick(x, y, size), 0
                    while answer is None:  # the GPU's answer comes with the facts, N frames later: nothing moves meanwhile
                        session.frame(target.framebuffer, 0.0)
                        waited += 1
                        answer = None if session._pick is not None else session.selected
                        assert waited <= session.pipeline.latency + 2
                    picks[path].append(answer)
    assert picks["cpu"] == picks["gpu"] and sum(p >= 0 for p in picks["gpu"]) > 5
