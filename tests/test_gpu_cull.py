"""Issue 19, points 1 and 2: the GPU-driven cull (a compute pass fills per-(piece, LOD) lists and
indirect commands) against the float64 CPU test it replaces, on llvmpipe."""

from __future__ import annotations

import numpy as np
import pytest

from crowd.anim.bake import bake
from crowd.anim.processor import AnimationProcessor
from crowd.draw.cpu_cull import sphere_visible
from crowd.draw.cull_lists import entry_agents
from crowd.draw.render import CrowdRenderer, RenderError
from crowd.draw.view import frustum_planes, view_proj
from crowd.frame import Camera, Instances
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import PipelineConfig
from crowd.smoke import run_headless
from crowd.stages import cull_path

SIZE = (320, 180)
LOD_DISTANCES = (14.0, 40.0, 90.0)
# float32 on the GPU against float64 here: a sphere this close to a plane, or a distance this close to
# a LOD boundary, may land on either side (positions are camera-relative, within 200 m).
BOUNDARY_M = 1e-3


@pytest.fixture(scope="module")
def stages(gl_context, zombie):
    baked = bake(zombie.skeleton, zombie.clips)
    proc = AnimationProcessor(gl_context, baked, 4)
    made = {path: CrowdRenderer(gl_context, zombie, lod_distances=LOD_DISTANCES,
                                shadows=True, culling=True, cull_path=path, weapons_visibility=True) for path in ("cpu", "gpu")}
    yield made
    for r in made.values():
        r.release()
    proc.release()


def crowd(rng, n, renderer, camera):
    """Agents scattered around the camera's view, a quarter of them put exactly on a frustum plane
    (their sphere touching it from outside) and some exactly at a LOD distance."""
    positions = np.column_stack([rng.uniform(-120, 120, n), np.zeros(n), rng.uniform(-120, 120, n)]) + camera.target * [1, 0, 1]
    scale = rng.uniform(0.8, 1.25, n).astype(np.float32)
    planes = frustum_planes(view_proj(camera))
    eye = np.asarray(camera.eye, np.float64)
    margin = 0.0  # shadows have lists of their own: the colour cull needs no margin
    for k in range(0, n, 4):  # slide agent k along the plane's normal until its sphere touches the plane
        plane = planes[k % 6]
        center = positions[k] - eye + renderer.bounds[0, :3] * scale[k]
        gap = center @ plane[:3] + plane[3] + renderer.bounds[0, 3] * scale[k] + margin
        positions[k] -= gap * plane[:3] / max(np.linalg.norm(plane[:3]), 1e-12)
    for k in range(2, n, 16):  # and some at a LOD boundary
        center = positions[k] - eye + renderer.bounds[0, :3] * scale[k]
        direction = center / np.linalg.norm(center)
        positions[k] += direction * (LOD_DISTANCES[k % 2] - np.linalg.norm(center))
    heads = rng.integers(0, len(renderer.groups[0]["head"]), n)
    return Instances(positions, rng.uniform(-np.pi, np.pi, n).astype(np.float32), scale, np.full((n, 4), 255, np.uint8), {"head": heads})


def reference(renderer, camera, instances):
    """float64: (visible, lod, signed distance to the nearest plane minus the radius, distance)."""
    eye = np.asarray(camera.eye, np.float64)
    scale = instances.scale.astype(np.float64)
    centers = instances.position - eye + renderer.bounds[0, :3] * scale[:, None]
    radii = renderer.bounds[0, 3] * scale
    planes = frustum_planes(view_proj(camera))
    visible = sphere_visible(planes, centers, radii)
    slack = np.min(centers @ planes[:, :3].T + planes[:, 3] + radii[:, None], axis=1)
    dist = np.linalg.norm(centers, axis=1)
    lod = np.minimum(np.searchsorted(np.asarray(LOD_DISTANCES), dist, side="right"), renderer.lod_count - 1)
    return visible, lod, slack, dist


@pytest.mark.parametrize("seed", range(6))
def test_gpu_visible_set_and_lods_equal_the_float64_test(stages, seed):
    rng = np.random.default_rng(seed)
    gpu = stages["gpu"]
    eye = np.array([rng.uniform(-50, 50), rng.uniform(2, 60), rng.uniform(-50, 50)]) + [1e5, 0, -3e4]  # far from the origin
    camera = Camera(eye=eye, target=eye + [rng.uniform(-40, 40), -rng.uniform(1, 30), rng.uniform(-40, 40)],
                    fov_y=float(rng.uniform(20, 90)), aspect=float(rng.uniform(0.5, 2.5)))
    instances = crowd(rng, 3000, gpu, camera)
    gpu.prepare(camera, instances)
    got = gpu.gpu.visible_agents() & 0xFFFF  # the low half: 1 + LOD, 0 where culled
    visible, lod, slack, dist = reference(gpu, camera, instances)
    near_plane = np.abs(slack) < BOUNDARY_M
    near_lod = np.min(np.abs(dist[:, None] - np.asarray(LOD_DISTANCES)[None]), axis=1) < BOUNDARY_M
    assert near_plane.sum() > 50 and near_lod.sum() > 20  # the boundaries are exercised
    assert np.array_equal((got > 0)[~near_plane], visible[~near_plane])
    both = (got > 0) & visible & ~near_lod
    assert np.array_equal(got[both] - 1, lod[both])
    assert 0.05 < visible.mean() < 0.95


def _doubtful(slack, dist) -> set:
    """Agents within BOUNDARY_M of a plane or a LOD distance: either side is right for them."""
    near_lod = np.min(np.abs(dist[:, None] - np.asarray(LOD_DISTANCES)), axis=1) < BOUNDARY_M
    return set(np.flatnonzero((np.abs(slack) < BOUNDARY_M) | near_lod).tolist())


def _lists(renderer, cascade: int | None = None) -> list[set]:
    """The agents in each draw's list in the view's pass (or a shadow cascade's), as the draws read them."""
    return [set(entry_agents(renderer.listed(k, cascade))[0].tolist()) for k in range(len(renderer.draws))]


def _prepared_on_both_paths(stages, camera, seed: int, agents: int):
    """(cpu renderer, gpu renderer, instances): one crowd() culled and listed by both paths."""
    cpu, gpu = stages["cpu"], stages["gpu"]
    instances = crowd(np.random.default_rng(seed), agents, gpu, camera)
    cpu.prepare(camera, instances)
    gpu.prepare(camera, instances)
    return cpu, gpu, instances


def test_each_draws_list_holds_the_agents_the_cpu_path_draws(stages):
    """Draw by draw, the GPU's list holds exactly the agents the CPU path puts in that draw, but for
    agents within BOUNDARY_M of a plane or a LOD distance; the counts in the commands match the lists."""
    camera = Camera(eye=np.array([0.0, 25.0, 60.0]), target=np.zeros(3), aspect=16 / 9)
    cpu, gpu, instances = _prepared_on_both_paths(stages, camera, seed=11, agents=5000)
    counts = gpu.gpu.counts(wait=True)
    assert [(d.piece, d.lod) for d in cpu.draws] == [(d.piece, d.lod) for d in gpu.draws]
    _, _, slack, dist = reference(gpu, camera, instances)
    doubtful = _doubtful(slack, dist)
    total = 0
    for k, (c, on_cpu, on_gpu) in enumerate(zip(cpu.draws, _lists(cpu), _lists(gpu))):
        assert len(on_gpu) == int(counts[k]) == len(gpu.listed(k))  # no agent twice in a list
        assert on_cpu - doubtful == on_gpu - doubtful, (c.piece, c.lod)
        total += len(on_cpu)
    assert total > 1000 and len(doubtful) < 0.2 * len(instances)


def test_the_stats_describe_the_last_frame_on_the_gpu_path(gl_context):
    """The GPU's counts trail the frame; a run's stats wait for them: a 1-frame run counts its agents,
    and a crowd resized to 0 counts none at once."""
    from crowd.gl import Offscreen
    from crowd.smoke import FIXED_DT

    one = {path: run_headless(PipelineConfig(agents=120, seed=2, cull=path), 1, SIZE, ctx=gl_context) for path in ("cpu", "gpu")}
    assert one["gpu"]["last_frame"] == one["cpu"]["last_frame"] and one["gpu"]["last_frame"]["instances"] > 0
    four = {path: run_headless(PipelineConfig(agents=120, seed=2, cull=path), 4, SIZE, ctx=gl_context) for path in ("cpu", "gpu")}
    assert four["gpu"]["weapons"]["drawn"] == four["cpu"]["weapons"]["drawn"] > 0  # read back 2 frames late: from frame 3
    with CrowdPipeline(gl_context, PipelineConfig(agents=200, cull="gpu")) as pipeline, Offscreen(gl_context, SIZE) as target:
        pipeline.camera = pipeline.default_camera(SIZE[0] / SIZE[1])
        for _ in range(3):
            pipeline.frame(target.framebuffer, FIXED_DT)
        pipeline.set("agents", 0)
        pipeline.frame(target.framebuffer, FIXED_DT)
        assert pipeline.renderer.last["instances"] == 0 and pipeline.renderer.last["triangles"] == 0


def test_lists_past_what_a_shader_may_address_are_one_line(gl_context, monkeypatch):
    with CrowdPipeline(gl_context, PipelineConfig(agents=10, cull="gpu", weapons=False)) as pipeline:
        monkeypatch.setattr(pipeline.renderer.gpu, "max_block", 1000)
        pipeline.set("agents", 50)
        from crowd.gl import Offscreen

        with Offscreen(gl_context, (32, 32)) as target, pytest.raises(RenderError, match=r"lists for 50 agents need [\d,]+ bytes, more than the 1,000 one shader storage block may hold on this GPU .*--cull feedback or cpu"):
            pipeline.frame(target.framebuffer, 1 / 30)


def test_switching_the_cull_path_live_leaks_nothing(gl_context):
    from test_architecture import gl_census

    from crowd.session import CrowdSession, SessionError
    from crowd.scene import Scene
    from crowd.gl import Offscreen

    before = gl_census()
    with Offscreen(gl_context, SIZE) as target:
        session = CrowdSession(gl_context, Scene(agents=60))
        try:
            for path, weapons, occlusion in (("cpu", True, True), ("gpu", False, True), ("gpu", True, False), ("cpu", False, False),
                                             ("feedback", True, True), ("feedback", False, False), ("auto", True, True), ("auto", True, False)):
                session.set("cull", path)
                session.set("weapons", weapons)
                session.set("occlusion", occlusion)
                session.frame(target.framebuffer, 1 / 30)
                session.frame(target.framebuffer, 1 / 30)
                renderer = session.pipeline.renderer
                assert (renderer.gpu is not None) == (path in ("gpu", "auto")) and (renderer.feedback is not None) == (path == "feedback")
                assert (renderer.pyramid is not None) == (occlusion and renderer.gpu is not None)
                assert session.to_scene().cull == path and session.to_scene().occlusion == occlusion
            with pytest.raises(SessionError, match="cull"):
                session.set("cull", "sideways")
        finally:
            session.release()
    assert gl_census() == before


@pytest.mark.parametrize("features", [{}, {"culling": False}, {"shadows": False, "weapons": False}, {"agents": 1}])
def test_the_picture_is_the_same_on_both_paths(gl_context, features):
    config = {"agents": 120, "seed": 7, **features, "ai_path": "cpu"}  # (the same crowd on both: the GPU AI needs the GPU cull)
    pictures = {path: run_headless(PipelineConfig(**config, cull=path), 3, SIZE, ctx=gl_context) for path in ("cpu", "gpu")}
    assert np.array_equal(pictures["cpu"]["_image"], pictures["gpu"]["_image"])
    # The GPU's counts trail by a frame or two; after 3 frames they are this crowd's.
    assert pictures["gpu"]["last_frame"]["instances"] == pictures["cpu"]["last_frame"]["instances"]
    assert ("cull" in pictures["gpu"]["passes_run"]) and ("cull" not in pictures["cpu"]["passes_run"])


def test_no_gpu_cull_storage_on_the_cpu_path_and_none_for_the_visibility_without_weapons(gl_context):
    cpu = run_headless(PipelineConfig(agents=50, cull="cpu"), 2, SIZE, ctx=gl_context)
    assert "cull" not in cpu["gpu_bytes"]
    with CrowdPipeline(gl_context, PipelineConfig(agents=50, cull="gpu", weapons=False)) as pipeline:
        assert pipeline.renderer.gpu.visible is None
    with CrowdPipeline(gl_context, PipelineConfig(agents=50, cull="gpu")) as pipeline:
        assert pipeline.renderer.gpu.visible is not None


def test_auto_picks_the_gpu_where_compute_exists_and_gpu_without_it_is_one_line():
    class Context:
        def __init__(self, version):
            self.version_code = version

    assert cull_path(Context(450), "auto") == "gpu" and cull_path(Context(330), "auto") == "cpu"
    assert cull_path(Context(330), "cpu") == "cpu"
    with pytest.raises(RenderError, match="the gpu cull path needs GL 4.3 compute shaders; this context is GL 330"):
        cull_path(Context(330), "gpu")


def test_resizing_the_gpu_cull_from_0_to_200000_and_back_leaks_nothing(gl_context):
    from test_architecture import gl_census

    before = gl_census()
    with CrowdPipeline(gl_context, PipelineConfig(agents=0, cull="gpu", shadows=False, occlusion=True)) as pipeline:
        from crowd.gl import Offscreen

        with Offscreen(gl_context, (64, 64)) as target:
            pipeline.camera = Camera(eye=np.array([0.0, 300.0, 0.0]), target=np.array([0.0, 400.0, 0.1]))  # high, at the sky: all culled
            for n in (0, 1, 200_000, 0):
                pipeline.set("agents", n)
                pipeline.frame(target.framebuffer, 1 / 30)
                gl_context.finish()
                cull = pipeline.renderer.gpu
                held = pipeline.renderer.gpu_bytes()
                assert cull.cast == (n,) and held["lists"] <= 64 * n + 4 and held["cull"] < 16384 + 4 * n
                assert int(cull.counts(wait=True).sum()) == 0
            assert pipeline.renderer.gpu_bytes()["cull"] < 16384 and pipeline.renderer.gpu_bytes()["lists"] == 4
    assert gl_census() == before


def test_a_weapon_is_drawn_exactly_when_its_agent_is(gl_context):
    """A camera that sees part of the crowd: the GPU path draws as many weapons as the CPU path, which
    uploads only the visible agents' weapons, and the pictures are the same."""
    from crowd.gl import Offscreen
    from crowd.smoke import FIXED_DT

    camera = Camera(eye=np.array([6.0, 1.7, 6.0]), target=np.array([14.0, 1.0, 2.0]), aspect=SIZE[0] / SIZE[1])
    drawn, pictures = {}, {}
    for path in ("cpu", "gpu"):
        with CrowdPipeline(gl_context, PipelineConfig(agents=300, seed=3, cull=path, ai_path="cpu")) as pipeline, Offscreen(gl_context, SIZE) as target:
            pipeline.camera = camera
            for _ in range(4):
                pipeline.frame(target.framebuffer, FIXED_DT)
            gl_context.finish()
            if path == "cpu":
                drawn[path] = pipeline.weapons.last["weapons"]
                placed = None
            else:
                commands = np.frombuffer(pipeline.weapons._commands.read(), np.uint32).reshape(-1, 5)
                drawn[path] = int(commands[:, 1].sum())
                placed = pipeline.weapons.last["weapons"]
            pictures[path] = target.image()
    assert 0 < drawn["gpu"] == drawn["cpu"] < placed  # some armed agents are out of view, and their weapons are not drawn
    assert np.array_equal(pictures["cpu"], pictures["gpu"])


# -- shadows: lists of their own, culled against the sun's volume, one LOD coarser


def _shadow_scene(gl_context, zombie, path, agents_x):
    """One frame of agents standing at x = agents_x (z = 0) under a low sun from +x (shadows 6.7 m long
    toward -x), seen by a camera whose view on the ground spans x from -15.7 to -2.3: the picture and the
    renderer's counts."""
    from crowd.gl import Offscreen
    from crowd.frame import empty_layers

    baked = bake(zombie.skeleton, zombie.clips)
    n = len(agents_x)
    with AnimationProcessor(gl_context, baked, 4) as proc, Offscreen(gl_context, SIZE) as target:
        proc.resize(n)
        layers = empty_layers(n, 4)
        layers[:, 0, 2] = 1.0  # clip 0 at phase 0, weight 1
        proc.process(layers)
        renderer = CrowdRenderer(gl_context, zombie, lod_distances=LOD_DISTANCES,
                                 shadows=True, culling=True, cull_path=path)
        try:
            renderer.sun_dir = np.array([1.0, 0.27, 0.0]) / np.linalg.norm([1.0, 0.27, 0.0])
            camera = Camera(eye=np.array([-9.0, 14.0, 0.0]), target=np.array([-9.0, 0.0, -0.01]), fov_y=30.0, aspect=SIZE[0] / SIZE[1])
            instances = Instances(np.column_stack([agents_x, np.zeros(n), np.zeros(n)]), np.zeros(n, np.float32),
                                  np.ones(n, np.float32), np.full((n, 4), 255, np.uint8), {"head": np.zeros(n, np.int64)})
            view = renderer.prepare(camera, instances)
            fb = target.framebuffer
            fb.use()
            fb.clear(0.5, 0.5, 0.5, 1.0, depth=1.0)
            renderer.shadow_pass(view, proc)
            renderer.color_pass(fb, view, proc)
            renderer.ground_pass(fb, view)
            gl_context.finish()
            renderer.refresh_counts(wait=True)
            return target.image().astype(int), dict(renderer.last)
        finally:
            renderer.release()


@pytest.mark.parametrize("path", ["cpu", "gpu"])
def test_an_agent_outside_the_view_still_shadows_into_it(gl_context, zombie, path):
    """The agent's sphere is several metres outside the view (the old 3 m margin would have dropped
    it): it is not drawn, but its shadow darkens the ground in view."""
    lit, lit_last = _shadow_scene(gl_context, zombie, path, np.array([200.0]))  # far away: no shadow in view
    shaded, last = _shadow_scene(gl_context, zombie, path, np.array([3.0]))  # about 4 m right of the view
    # Not drawn in colour; the body (its shirt merged in) and the head in the shadow lists of one cascade or both.
    assert last["instances"] == 0 and last["shadow_instances"] in (2, 4)
    darker = (lit - shaded).max(axis=2) > 10
    assert darker.mean() > 0.002 and not np.any((shaded - lit).max(axis=2) > 10)  # a shadow, and nothing brighter


@pytest.mark.parametrize("shadows", [True, False])
def test_shadow_lists_exist_only_with_shadows(gl_context, shadows):
    from crowd.draw.shadows import CASCADES

    for path in ("cpu", "gpu"):
        with CrowdPipeline(gl_context, PipelineConfig(agents=20, cull=path, shadows=shadows, weapons=False)) as pipeline:
            r = pipeline.renderer
            cull = r.gpu if path == "gpu" else r.cpu
            assert cull.cascades == (CASCADES if shadows else 0)
            if path == "cpu":
                assert len(cull.buffers) == 1 + cull.cascades


def cascade_slack(renderer, camera, instances):
    """float64, per shadow cascade: (cascade, the agents' distances from the eye, each agent's margin inside
    the cascade's box and its reach (negative: outside)). The first character's bound for every agent."""
    eye = np.asarray(camera.eye, np.float64)
    scale = instances.scale.astype(np.float64)
    centers = instances.position - eye + renderer.bounds[0, :3] * scale[:, None]
    radii = renderer.bounds[0, 3] * scale
    dist = np.linalg.norm(centers, axis=1)
    shadow = renderer.light_cascades(camera, instances)
    for cascade, (matrix, reach) in enumerate(zip(shadow.view_proj, shadow.reach_m)):
        light = frustum_planes(matrix)
        # Inside the cascade's box, and near enough to the eye to shadow what it covers.
        yield cascade, dist, np.minimum(np.min(centers @ light[:, :3].T + light[:, 3] + radii[:, None], axis=1), float(reach) - (dist - radii))


def test_shadow_lists_are_each_cascades_agents_one_lod_coarser(stages):
    """Per cascade and draw, the GPU's shadow list holds the CPU path's (agents away from the
    boundaries) and no agent outside the cascade's box; each agent casts its shadow from one LOD
    coarser than the colour pass would draw it (capped)."""
    camera = Camera(eye=np.array([0.0, 12.0, 30.0]), target=np.zeros(3), aspect=16 / 9)
    cpu, gpu, instances = _prepared_on_both_paths(stages, camera, seed=5, agents=4000)
    per_cascade = []
    for cascade, dist, slack in cascade_slack(gpu, camera, instances):
        colour_lod = np.minimum(np.searchsorted(np.asarray(LOD_DISTANCES), dist, side="right"), gpu.lod_count - 1)
        shadow_lists = _lists(gpu, cascade)
        doubtful = _doubtful(slack, dist)
        casting = 0
        for k, (c, g, on_cpu, on_gpu) in enumerate(zip(cpu.draws, gpu.draws, _lists(cpu, cascade), shadow_lists)):
            assert on_cpu - doubtful == on_gpu - doubtful, (cascade, c.piece, c.lod)
            for a in on_gpu - doubtful:
                assert g.lod == min(colour_lod[a] + 1, gpu.lod_count - 1)
            casting += len(on_gpu)
        assert set(np.flatnonzero(slack < -BOUNDARY_M).tolist()).isdisjoint(set().union(*shadow_lists))
        per_cascade.append(casting)
    # The near cascade holds the agents around the target; the crowd's cascade holds more of them.
    assert 100 < per_cascade[0] < per_cascade[1]


def test_agents_past_the_fog_cast_nothing_into_the_far_cascade(stages):
    """The far cascade ends where fog leaves a tenth of a shadow's contrast: an agent in view well past
    that distance is in neither path's far shadow list, one in view nearer is, in both."""
    camera = Camera(eye=np.array([0.0, 30.0, 0.0]), target=np.array([0.0, 0.0, -400.0]), aspect=16 / 9, far=3000.0)
    for path in ("cpu", "gpu"):
        r = stages[path]
        r.crowd_box = (np.array([-50.0, 0.0, -1500.0]), np.array([50.0, 0.0, 0.0]))
        found = []
        for z in (-300.0, -1200.0):
            instances = Instances(np.array([[0.0, 0.0, z]]), np.zeros(1, np.float32), np.ones(1, np.float32),
                                  np.full((1, 4), 255, np.uint8), {"head": np.zeros(1, np.int64)})
            view = r.prepare(camera, instances)
            r.refresh_counts(wait=True)
            far = sum(d.shadow_counts[1] for d in r.draws)
            assert (view.visible is None or view.visible[0]) and r.last["visible"] == 1
            found.append(far)
            if view.casting is not None:
                assert bool(view.casting[1][0]) == (far > 0)
        r.crowd_box = None
        assert found[0] > 0 and found[1] == 0, (path, found)
        assert r.light_cascades(camera).reach_m[1] < 700.0


def test_weapons_are_drawn_at_their_agents_lod_on_both_paths(gl_context):
    """Per (weapon, LOD) draw, the GPU path draws exactly as many weapons as the CPU path, colour and
    shadow; and the CPU path's are the visible armed agents at min(their LOD, the weapon's coarsest)."""
    from crowd.gl import Offscreen
    from crowd.smoke import FIXED_DT

    counts = {}
    for path in ("cpu", "gpu"):
        config = PipelineConfig(agents=400, seed=5, cull=path, lod_distances=(6.0, 12.0, 20.0))
        with CrowdPipeline(gl_context, config) as pipeline, Offscreen(gl_context, SIZE) as target:
            pipeline.camera = Camera(eye=np.array([0.0, 2.0, 30.0]), target=np.array([0.0, 1.0, 0.0]), aspect=SIZE[0] / SIZE[1])
            for _ in range(4):
                pipeline.frame(target.framebuffer, FIXED_DT)
            gl_context.finish()
            pipeline.refresh_counts()
            w = pipeline.weapons
            if path == "gpu":
                colour = np.frombuffer(w._commands.read(), np.uint32).reshape(-1, 5)[:, 1]
                shadow = np.frombuffer(w._shadow_commands.read(), np.uint32).reshape(-1, 5)[:, 1]
            else:
                colour = np.array([m["count"] for m in w._meshes])
                shadow = np.array([m["shadow_counts"] for m in w._meshes]).T.reshape(-1)  # cascade-major, as the GPU's
                agents, weapon, _ = w.drawn
                lod = np.minimum(pipeline.last.view.lod[agents], w.lod_count - 1)
                expected = np.bincount(weapon * w.lod_count + lod, minlength=len(w._meshes))
                np.testing.assert_array_equal(colour, expected)
                assert np.count_nonzero(colour) >= 4  # several LODs in play
            counts[path] = (colour.tolist(), shadow.tolist())
    assert counts["gpu"] == counts["cpu"]


@pytest.mark.parametrize("path", ["cpu", "gpu"])
def test_weapons_shadow_with_their_agents_not_with_the_view(gl_context, path):
    """A camera that sees part of the crowd: the weapons' shadow pass draws the weapons of the agents
    in the sun's volume (some out of view), the colour pass those of the agents drawn."""
    from crowd.gl import Offscreen
    from crowd.smoke import FIXED_DT

    camera = Camera(eye=np.array([6.0, 1.7, 6.0]), target=np.array([14.0, 1.0, 2.0]), aspect=SIZE[0] / SIZE[1])
    with CrowdPipeline(gl_context, PipelineConfig(agents=300, seed=3, cull=path)) as pipeline, Offscreen(gl_context, SIZE) as target:
        pipeline.camera = camera
        for _ in range(4):
            pipeline.frame(target.framebuffer, FIXED_DT)
        gl_context.finish()
        w = pipeline.weapons
        from crowd.draw.shadows import CASCADES

        if path == "gpu":
            colour = int(np.frombuffer(w._commands.read(), np.uint32).reshape(-1, 5)[:, 1].sum())
            per_cascade = np.frombuffer(w._shadow_commands.read(), np.uint32).reshape(CASCADES, -1, 5)[:, :, 1].sum(axis=1)
            visible = pipeline.renderer.gpu.visible_agents()
        else:
            colour = sum(m["count"] for m in w._meshes)
            per_cascade = np.sum([m["shadow_counts"] for m in w._meshes], axis=0)
        shadow = int(per_cascade.sum())
        armed = set(w.drawn[0].tolist())  # GPU path: every placed weapon's agent
        assert shadow > 0 and colour > 0 and shadow != colour
        if path == "gpu":  # per cascade: every placed weapon whose agent is in its volume, and no other
            for k in range(CASCADES):
                assert per_cascade[k] == sum(1 for a in armed if visible[a] & (0x10000 << k))
