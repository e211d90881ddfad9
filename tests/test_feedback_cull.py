"""Issue 25, point 2: the cull of GL 4.0 to 4.2 contexts (macOS's 4.1), by transform feedback, drawn
with glDrawElementsIndirect: its lists against the CPU path's and its visibility against the compute
cull's, agent by agent, on llvmpipe; the whole frame against the other two paths' pictures; and its
storage over a resize."""

from __future__ import annotations

import numpy as np
import pytest

from crowd.anim.bake import bake
from crowd.anim.processor import AnimationProcessor
from crowd.draw.cull_lists import entry_agents
from crowd.draw.render import CrowdRenderer, RenderError
from crowd.frame import Camera, Instances
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import PipelineConfig
from crowd.smoke import run_headless
from crowd.stages import cull_path
from test_gpu_cull import BOUNDARY_M, LOD_DISTANCES, _doubtful, _lists, cascade_slack, crowd, reference

SIZE = (320, 180)
FADE_M = 3.0


@pytest.fixture(scope="module")
def renderers(gl_context, zombie):
    """The CPU path's and the feedback path's renderers (and the compute path's where GL 4.3 exists), with
    a LOD fade, shadows and each agent's visibility kept for the weapons."""
    baked = bake(zombie.skeleton, zombie.clips)
    proc = AnimationProcessor(gl_context, baked, 4)
    paths = ("cpu", "feedback", "gpu") if gl_context.version_code >= 430 else ("cpu", "feedback")
    made = {path: CrowdRenderer(gl_context, zombie, lod_distances=LOD_DISTANCES, shadows=True, culling=True, cull_path=path,
                                weapons_visibility=True, lod_fade=FADE_M) for path in paths}
    yield made
    for r in made.values():
        r.release()
    proc.release()


def _prepared(renderers, camera, seed: int, agents: int):
    instances = crowd(np.random.default_rng(seed), agents, renderers["feedback"], camera)
    for r in renderers.values():
        r.prepare(camera, instances)
    return instances


def _codes(renderer, k: int) -> dict:
    """{agent: the fade code of its entry} of draw k's list in the view's pass."""
    agents, codes = entry_agents(renderer.listed(k))
    return dict(zip(agents.tolist(), codes.tolist()))


def _doubtful_with_fades(instances, renderer, camera) -> set:
    _, _, slack, dist = reference(renderer, camera, instances)
    near_fade_end = np.min(np.abs(dist[:, None] - (np.asarray(LOD_DISTANCES) + FADE_M)), axis=1) < BOUNDARY_M
    return _doubtful(slack, dist) | set(np.flatnonzero(near_fade_end).tolist())


@pytest.mark.parametrize("seed", range(3))
def test_each_list_holds_the_cpu_paths_agents_with_their_fade_codes(renderers, seed):
    """Draw by draw, the feedback list holds exactly the agents the CPU path draws there, each with the
    same fade code (both LODs across a fade band), but for agents within BOUNDARY_M of a plane, a LOD
    distance or a fade band's end; the commands count what the lists hold."""
    camera = Camera(eye=np.array([0.0, 25.0, 60.0]), target=np.zeros(3), aspect=16 / 9)
    instances = _prepared(renderers, camera, seed, 5000)
    cpu, fb = renderers["cpu"], renderers["feedback"]
    counts = fb.feedback.counts(wait=True)
    doubtful = _doubtful_with_fades(instances, fb, camera)
    total = fading = 0
    for k, draw in enumerate(cpu.draws):
        on_cpu = _codes(cpu, k)
        on_gpu = _codes(fb, k)
        assert len(on_gpu) == int(counts[k])  # no agent twice in a list
        keep = lambda codes: {a: c for a, c in codes.items() if a not in doubtful}  # noqa: E731
        assert keep(on_cpu) == keep(on_gpu), (draw.piece, draw.lod)
        total += len(on_cpu)
        fading += sum(1 for c in on_cpu.values() if c != 255)
    assert total > 1000 and fading > 50 and len(doubtful) < 0.25 * len(instances)


def test_shadow_lists_hold_the_cpu_paths_agents(renderers):
    """Per cascade and draw, the feedback shadow list holds the CPU path's agents (away from the
    boundaries of the view, the LODs and the cascades' boxes)."""
    camera = Camera(eye=np.array([0.0, 12.0, 30.0]), target=np.zeros(3), aspect=16 / 9)
    instances = _prepared(renderers, camera, 5, 4000)
    cpu, fb = renderers["cpu"], renderers["feedback"]
    casting = []
    for cascade, dist, slack in cascade_slack(fb, camera, instances):
        doubtful = _doubtful(slack, dist)
        found = 0
        for k, (draw, on_cpu, on_gpu) in enumerate(zip(cpu.draws, _lists(cpu, cascade), _lists(fb, cascade))):
            assert on_cpu - doubtful == on_gpu - doubtful, (cascade, draw.piece, draw.lod)
            found += len(on_gpu)
        casting.append(found)
    assert 100 < casting[0] < casting[1]


def test_the_visibility_the_weapons_read_is_the_compute_culls(renderers):
    """Each agent's visibility word (colour LOD + 1, 0 where culled; each cascade it casts into, with its
    shadow LOD) is the compute cull's, but for agents at a boundary."""
    if "gpu" not in renderers:
        pytest.skip("the compute cull needs GL 4.3")
    camera = Camera(eye=np.array([0.0, 12.0, 30.0]), target=np.zeros(3), aspect=16 / 9)
    instances = _prepared(renderers, camera, 8, 4000)
    fb, gpu = renderers["feedback"], renderers["gpu"]
    mine, theirs = fb.feedback.visible_agents(), gpu.gpu.visible_agents()
    _, _, slack, dist = reference(fb, camera, instances)
    sure = np.ones(len(instances), bool)
    sure[list(_doubtful(slack, dist))] = False
    # (the cascades' boundaries are not in `slack`: a word may differ there, in its cascade bits only)
    assert np.array_equal(mine[sure] & 0xFFFF, theirs[sure] & 0xFFFF)
    assert np.mean(mine[sure] == theirs[sure]) > 0.97
    assert (mine & 0xFFFF).any() and (mine >> 16).any()


def test_every_agent_of_a_big_list_is_counted_exactly(gl_context, zombie):
    """Culling off, 70,000 agents at LOD0: the additive float counts are exact (integers below 2^24 per
    texel), so each command draws every agent, and each list holds each agent once."""
    with CrowdRenderer(gl_context, zombie, lod_distances=(1e6, 2e6, 3e6), shadows=False, culling=False, cull_path="feedback") as r:
        n = 70_000
        rng = np.random.default_rng(1)
        heads = rng.integers(0, len(r.groups[0]["head"]), n)
        instances = Instances(np.column_stack([rng.uniform(-50, 50, n), np.zeros(n), rng.uniform(-50, 50, n)]),
                              np.zeros(n, np.float32), np.ones(n, np.float32), np.full((n, 4), 255, np.uint8), {"head": heads})
        r.prepare(Camera(eye=np.array([0.0, 5.0, 80.0]), target=np.zeros(3)), instances)
        counts = r.feedback.counts(wait=True)
        for k, draw in enumerate(r.draws):
            want = n if draw.group < 0 else int(np.sum(heads == draw.choice))
            assert int(counts[k]) == (want if draw.lod == 0 else 0), (draw.piece, draw.lod)
        body = next(k for k, d in enumerate(r.draws) if d.piece == "body" and d.lod == 0)
        assert len(set(entry_agents(r.listed(body))[0].tolist())) == n
        r.refresh_counts(wait=True)
        assert r.last["visible"] == n and r.last["lod_counts"][0] == n


@pytest.mark.parametrize("features", [{}, {"culling": False}, {"shadows": False, "weapons": False}, {"agents": 1},
                                      {"impostors": "on", "impostor_distance": 30.0, "lod_fade": 2.0, "agents": 600}])
def test_the_picture_and_stats_are_the_cpu_paths(gl_context, no_compute_features, tmp_path, monkeypatch, features):
    """The same crowd culled on the CPU and by transform feedback (every GL 4.3 entry point refused while
    the feedback path runs): the same picture, to the bit, and the same counts once the GPU's have come back."""
    monkeypatch.setenv("CROWD_CACHE_DIR", str(tmp_path))
    config = {"agents": 120, "seed": 7, "gl": "4.1", **features}
    cpu = run_headless(PipelineConfig(**config, cull="cpu"), 4, SIZE, ctx=gl_context)
    fb = run_headless(PipelineConfig(**config, cull="feedback"), 4, SIZE, ctx=gl_context)
    assert fb["cull_path"] == "feedback" and "cull" in fb["passes_run"] and "cull" not in cpu["passes_run"]
    assert np.array_equal(cpu["_image"], fb["_image"])
    assert fb["last_frame"] == cpu["last_frame"]
    if config.get("weapons", True):
        assert fb["weapons"]["drawn"] == cpu["weapons"]["drawn"] and fb["weapons"]["triangles"] == cpu["weapons"]["triangles"]


def test_auto_takes_the_feedback_cull_on_gl_40_to_42():
    class Context:
        def __init__(self, version):
            self.version_code = version

    assert [cull_path(Context(v), "auto") for v in (330, 400, 410, 420, 430, 450)] == ["cpu", "feedback", "feedback", "feedback", "gpu", "gpu"]
    assert cull_path(Context(450), "auto", 410) == "feedback" and cull_path(Context(450), "feedback") == "feedback"
    with pytest.raises(RenderError, match="the feedback cull path needs GL 4.0 indirect draws; this context is GL 330"):
        cull_path(Context(330), "feedback")


def test_resizing_the_feedback_cull_from_0_to_200000_and_back_leaks_nothing(gl_context):
    from crowd.gl import Offscreen
    from test_architecture import gl_census

    before = gl_census()
    with CrowdPipeline(gl_context, PipelineConfig(agents=0, cull="feedback", processor_path="fragment", impostors="off")) as pipeline:
        with Offscreen(gl_context, (64, 64)) as target:
            pipeline.camera = Camera(eye=np.array([0.0, 300.0, 0.0]), target=np.array([0.0, 400.0, 0.1]))  # high, at the sky: all culled
            fixed = None  # the counts, the commands and an entry's worth of each list: what no agents cost
            for n in (0, 1, 200_000, 0):
                pipeline.set("agents", n)
                pipeline.frame(target.framebuffer, 1 / 30)
                gl_context.finish()
                cull = pipeline.renderer.feedback
                held = pipeline.renderer.gpu_bytes()
                fixed = held["cull"] if fixed is None else fixed
                assert cull.cast == (n,) and held["lists"] == 4 * sum(max(cull.cast[key.character], 1) for key, _ in cull.slots)
                assert held["cull"] <= fixed + 4 * n + 4 * (n + 2048)  # the agents' indices, their visibility
                assert int(cull.counts(wait=True).sum()) == 0
            assert pipeline.renderer.gpu_bytes()["cull"] == fixed < 4 << 20
    assert gl_census() == before


def test_the_visibility_texture_exists_only_with_weapons(gl_context):
    from crowd.gl import Offscreen

    with Offscreen(gl_context, (64, 64)) as target, \
            CrowdPipeline(gl_context, PipelineConfig(agents=50, cull="feedback", processor_path="fragment")) as pipeline:
        pipeline.frame(target.framebuffer, 1 / 30)
        assert pipeline.renderer.feedback.visible is not None
        pipeline.set("weapons", False)
        assert pipeline.renderer.feedback.visible is None
        pipeline.frame(target.framebuffer, 1 / 30)
        pipeline.set("weapons", True)
        pipeline.frame(target.framebuffer, 1 / 30)
        words = pipeline.renderer.feedback.visible_agents()
        assert len(words) == pipeline.renderer.feedback.agents >= 50 and (words & 0xFFFF).any()


def test_the_benchmark_lists_what_the_compute_cull_lists(gl_context):
    """crowd-bench feedback on a small crowd: both culls list the same records, and every kind of point
    draw its floor times runs."""
    from bench.feedback_probe import VARIANTS, floor, measure

    row = measure(gl_context, [500], repeats=1)[0]
    assert all(f"{name}_ms" in row for name in VARIANTS if name != "compute" or gl_context.version_code >= 430)
    if gl_context.version_code >= 430:
        assert row["feedback_listed"] == row["compute_listed"] > 0
    assert row["lists"] >= row["feedback_draws"] > 0
    kinds = floor(gl_context, 1000, repeats=1)
    assert set(kinds) == {"points", "feedback_geometry_shader_ms", "feedback_vertex_shader_ms", "geometry_shader_ms", "points_ms"}


def test_a_crowd_gone_to_zero_leaves_no_commands_behind(gl_context):
    """The passes draw from the commands without knowing what they hold: once the crowd (and with it every
    placed weapon) is gone, every command draws nothing and nothing casts a shadow, and the picture is
    the CPU path's (stale commands would draw the last crowd's lists)."""
    from crowd.draw.feedback_cull import COMMAND_DTYPE
    from crowd.gl import Offscreen

    images = {}
    for path in ("cpu", "feedback"):
        with Offscreen(gl_context, SIZE) as target, CrowdPipeline(gl_context, PipelineConfig(agents=200, seed=2, cull=path, gl="4.1", survivor=False)) as p:
            for _ in range(4):
                p.frame(target.framebuffer, 1 / 30)
            if path == "feedback":
                assert p.weapons.casts_shadows() and int(p.renderer.feedback.counts(wait=True).sum()) > 0
            p.set("agents", 0)
            p.frame(target.framebuffer, 1 / 30)
            images[path] = target.image()
            if path == "feedback":
                assert not p.weapons.casts_shadows() and all(m["count"] == 0 for m in p.weapons._meshes)
                for commands in (p.renderer.feedback.counter.commands, p.weapons._counter.commands):
                    words = np.frombuffer(commands.read(), np.uint32)[: commands.size // 4 // 5 * 5].reshape(-1, 5)
                    assert not words[:, 1].any()
    assert np.array_equal(images["cpu"], images["feedback"])
