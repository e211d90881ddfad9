"""Headless smoke mode, the frame pipeline and the renderer on llvmpipe."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import PipelineConfig, PipelineError
from crowd.settings import SettingError, parse
from crowd.frame import Camera, FrameError, Instances
from crowd.draw.cpu_cull import sphere_visible
from crowd.draw.render import CrowdRenderer
from crowd.draw.view import frustum_planes, view_proj
from crowd.anim.roles import RoleError, clips_used, match_roles, parse_overrides
from crowd.gl import Offscreen
from crowd.smoke import FIXED_DT, run_headless
from conftest import ROOT, shared

SIZE = (320, 180)


@pytest.mark.parametrize("cull, gl", [("cpu", "auto"), ("gpu", "auto"), ("auto", "4.1")])
def test_smoke_frame_shows_zombies_where_they_stand(gl_context, cull, gl):
    pipeline = CrowdPipeline(gl_context, PipelineConfig(agents=40, seed=3, cull=cull, gl=gl))
    target = Offscreen(gl_context, SIZE)
    fb = target.framebuffer
    try:
        pipeline.camera = pipeline.default_camera(SIZE[0] / SIZE[1])
        for _ in range(3):
            pipeline.frame(fb, FIXED_DT)
        crowd = target.image().astype(int)
        hips = pipeline.project(pipeline.joint_world_positions(0), SIZE)
        pipeline.set("agents", 0)  # same camera, same ground, no zombies
        pipeline.frame(fb, FIXED_DT)
        empty = target.image().astype(int)
        assert "process" in pipeline.passes_run and "draw" in pipeline.passes_run
    finally:
        pipeline.release()
        target.release()
    changed = np.any(np.abs(crowd - empty) > 12, axis=2)
    assert changed.mean() > 0.02  # zombies (and their shadows) cover a visible share of the frame
    inside = [(x, y) for x, y in hips if 1 <= x < SIZE[0] - 1 and 1 <= y < SIZE[1] - 1]
    assert len(inside) >= 30
    covered = [changed[int(y) - 1 : int(y) + 2, int(x) - 1 : int(x) + 2].any() for x, y in inside]
    assert np.mean(covered) > 0.9  # each agent's projected hips land on its drawn body


@pytest.mark.parametrize("agents", [0, 1])
def test_zero_and_one_agent(tmp_path, gl_context, agents):
    # (No LOD fade: an agent within its band of a switch is drawn at both LODs, its pieces twice.)
    stats = run_headless(PipelineConfig(agents=agents, lod_fade=0.0), 3, SIZE, tmp_path / "a.png", tmp_path / "a.json", ctx=gl_context)
    saved = json.loads((tmp_path / "a.json").read_text())
    assert saved["agents"] == agents and saved["nan_count"] == 0
    assert saved["cpu_ms"] > 0  # the main thread's CPU time a frame, 0 agents too
    assert ("process" in saved["passes_run"]) == (agents > 0)
    assert ("draw" in saved["passes_run"]) == (agents > 0)
    assert (saved["gpu_bytes"]["palette"] > 0) == (agents > 0)
    assert (tmp_path / "a.png").stat().st_size > 1000
    assert stats["last_frame"]["instances"] == (2 * agents)  # the body (its shirt merged in at import) and the head


def test_stats_fields_and_no_shadow_resources_when_shadows_are_off(tmp_path, gl_context):
    stats = run_headless(PipelineConfig(agents=20, shadows=False), 4, SIZE, None, tmp_path / "s.json", ctx=gl_context)
    saved = json.loads((tmp_path / "s.json").read_text())
    for key in ("gl_renderer", "gl_version", "agents", "frames", "size", "frame_period_ms", "frame_latency_ms", "passes_ms", "passes_run", "gpu_bytes", "nan_count"):
        assert key in saved, key
    # 4 frames: 2 back to back (the first dropped: it compiles shaders), then 2 with a finish each.
    assert saved["frame_period_ms"]["frames"] == 1 and saved["frame_latency_ms"]["frames"] == 2
    for key in ("frame_period_ms", "frame_latency_ms"):
        assert set(saved[key]) == {"p50", "p95", "max", "frames"} and saved[key]["p50"] > 0
    assert saved["passes_clock"]["process"] == "gpu" and saved["passes_ms"]["process"] > 0
    assert saved["passes_clock"]["ai"] == "cpu" and saved["passes_ms"]["ai"] > 0  # the crowd AI's CPU ms per frame
    assert saved["ai"]["faults"] == [] and sum(saved["ai"]["states"].values()) == 20
    assert saved["ai"]["think_budget"] == {"on": False, "exact": 20}  # 20 zombies: below think_from, everyone exact
    assert "shadow" not in saved["passes_run"] and "shadow_map" not in saved["gpu_bytes"] or saved["gpu_bytes"]["shadow_map"] == 0
    assert saved["bake"]["clips"] == ["idle", "shamble", "run", "attack", "hit", "death"]  # crawl is not used: not baked
    assert stats["nan_count"] == 0


def test_processor_paths_draw_the_same_frame(gl_context):
    images = {}
    for path in ("compute", "fragment"):
        # The foot lock runs on the compute path only: compared without it, the paths draw alike.
        stats = run_headless(PipelineConfig(agents=30, processor_path=path, foot_lock=False), 2, SIZE, ctx=gl_context)
        assert stats["processor_path"] == path
        images[path] = stats["_image"].astype(int)
    assert np.max(np.abs(images["compute"] - images["fragment"])) <= 1


def test_cli_writes_png_and_json(tmp_path):
    out = subprocess.run([sys.executable, "-m", "app.demo", "--headless", "--frames", "3", "--agents", "12", "--size", "160x90",
                          "--screenshot", str(tmp_path / "x.png"), "--stats", str(tmp_path / "x.json"), "--seed", "4"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert json.loads((tmp_path / "x.json").read_text())["size"] == [160, 90]
    assert (tmp_path / "x.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("args, words", [
    (["--model", "missing.glb"], "no such file"),
    (["--size", "12"], "size must"),
    (["--agents", "-3"], "--agents"),
    (["--roles", "walk"], "role overrides"),
    (["--frames", "0"], "--frames"),
])
def test_cli_bad_arguments_exit_nonzero_with_one_line(tmp_path, args, words):
    out = subprocess.run([sys.executable, "-m", "app.demo", "--headless", "--screenshot", str(tmp_path / "x.png"), *args],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2
    assert words in out.stderr and "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x.png").exists()


def test_cli_bad_model_file(tmp_path):
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"glTF\x02\x00\x00\x00garbage")
    out = subprocess.run([sys.executable, "-m", "app.demo", "--headless", "--model", str(bad), "--screenshot", str(tmp_path / "x.png")],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1


def test_imported_model_runs_through_the_pipeline(tmp_path, gl_context):
    path = shared("Quaternius_Zombie_Basic.gltf")
    stats = run_headless(PipelineConfig(agents=8, model=path, processor_path="fragment"), 2, SIZE, ctx=gl_context)
    assert stats["roles"]["walk"] == "Walk" and stats["roles"]["death"] == "Death"
    assert stats["nan_count"] == 0 and stats["last_frame"]["instances"] >= 8


def test_roles_match_by_name_and_can_be_overridden(zombie):
    roles, notes = match_roles(zombie.clips)
    assert roles == {"idle": "idle", "walk": "shamble", "run": "run", "attack": "attack", "hit": "hit", "death": "death"} and not notes
    assert "crawl" not in clips_used(roles)

    class C:
        def __init__(self, name, loop=True):
            self.name, self.loop = name, loop

    roles, _ = match_roles([C("Run_Gun"), C("Walk_Gun"), C("Run"), C("Walking"), C("Idle_Attack"), C("Idle"), C("Zombie_Death", False)])
    assert roles["run"] == "Run" and roles["walk"] == "Walking" and roles["idle"] == "Idle" and roles["death"] == "Zombie_Death"
    roles, notes = match_roles([C("clip0")])
    assert roles["walk"] == roles["idle"] == roles["run"] == "clip0" and roles["attack"] is None and notes
    # A creature of actions and one flying loop flies, whether or not its bite looks looped.
    roles, notes = match_roles([C("Bite"), C("Death", False), C("Hit", False), C("Flying")])
    assert roles["walk"] == roles["idle"] == roles["run"] == "Flying" and roles["attack"] == "Bite" and "'Flying'" in notes[0]
    roles, _ = match_roles([C("Bite"), C("Hurt", False), C("Glide", False), C("Soar")])
    assert roles["walk"] == "Soar"
    roles, _ = match_roles([C("Bite"), C("Glide", False)])  # no loop but the bite: the clip that is not an action
    assert roles["walk"] == "Glide"
    roles, _ = match_roles([C("Bite"), C("Stab", False)])  # nothing but actions: the looping one
    assert roles["walk"] == "Bite"
    roles, _ = match_roles([C("Walk"), C("Shuffle")], parse_overrides("walk=Shuffle"))
    assert roles["walk"] == "Shuffle"
    with pytest.raises(RoleError, match="no clip named"):
        match_roles([C("Walk")], {"walk": "Run"})
    with pytest.raises(RoleError, match="unknown role"):
        parse_overrides("dance=Walk")


def test_frustum_culling_and_render_input_checks(gl_context, zombie):
    cam = Camera(eye=np.array([0.0, 2.0, 10.0]), target=np.array([0.0, 1.0, 0.0]))
    planes = frustum_planes(view_proj(cam))
    centers = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 20.0], [100.0, 1.0, 0.0], [0.0, 1.0, -300.0]]) - cam.eye
    assert sphere_visible(planes, centers, np.ones(4)).tolist() == [True, False, False, True]
    renderer = CrowdRenderer(gl_context, zombie, shadows=False)
    try:
        n = 2
        good = Instances(np.zeros((n, 3)), np.zeros(n, np.float32), np.ones(n, np.float32), np.full((n, 4), 255, np.uint8), {"head": np.array([0, 1])})
        renderer.prepare(cam, good)
        assert renderer.last["instances"] == 4  # each agent's body (the shirt merged in) and head
        bad = Instances(np.full((n, 3), np.nan), good.yaw, good.scale, good.tint)
        with pytest.raises(FrameError, match="finite"):
            renderer.prepare(cam, bad)
        with pytest.raises(FrameError, match="variant"):
            renderer.prepare(cam, Instances(good.position, good.yaw, good.scale, good.tint, {"head": np.array([0, 5])}))
        with pytest.raises(FrameError, match="coincide"):
            renderer.prepare(Camera(eye=np.zeros(3), target=np.zeros(3)), good)
    finally:
        renderer.release()


def test_far_from_origin_agents_render_like_near_ones(gl_context):
    """Camera-relative positions: the same crowd 1e5 m away draws the same picture."""
    images = []
    for offset in (0.0, 1.0e5):
        pipeline = CrowdPipeline(gl_context, PipelineConfig(agents=9, seed=2, origin=(offset, -offset)))
        target = Offscreen(gl_context, SIZE)
        fb = target.framebuffer
        try:
            pipeline.camera = pipeline.default_camera(SIZE[0] / SIZE[1])
            pipeline.frame(fb, 0.0)
            images.append(target.image().astype(int))
        finally:
            pipeline.release()
            target.release()
    # The ground grid is anchored to the world, so it may shift; the zombies must not.
    diff = np.abs(images[0] - images[1]).max(axis=2)
    assert np.mean(diff > 40) < 0.01


def test_pipeline_config_errors(gl_context):
    with pytest.raises(PipelineError, match="agent count"):
        CrowdPipeline(gl_context, PipelineConfig(agents=-1))
    with pytest.raises(SettingError):
        parse("size", "0x0")


def test_triangle_reorder_keeps_the_mesh_and_shades_fewer_vertices(zombie):
    from crowd.asset.vertex_cache import optimize_triangle_order, shaded_vertices_per_triangle

    body = next(m for m in zombie.meshes if m.piece == "body" and m.lod == 0)
    order = optimize_triangle_order(body.indices, len(body.positions))
    canon = lambda idx: sorted(tuple(np.roll(t, -int(np.argmin(t)))) for t in idx.reshape(-1, 3))  # noqa: E731
    assert canon(order) == canon(body.indices)  # same triangles, same winding
    assert shaded_vertices_per_triangle(order) < 0.95 * shaded_vertices_per_triangle(body.indices)


def test_triangle_reorder_takes_the_best_of_the_rest_without_scanning_them_all():
    """Each time the cache runs dry the order starts from the best triangle left. A mesh of many parts (a
    merged modular character) runs dry once a part, and one whose triangles share no vertex once a
    triangle: scanning every triangle each time made it quadratic (minutes for these 30,000)."""
    import time

    from crowd.asset.vertex_cache import optimize_triangle_order

    lone = np.arange(3 * 30_000, dtype=np.uint32)
    start = time.perf_counter()
    order = optimize_triangle_order(lone, len(lone))
    assert time.perf_counter() - start < 20.0
    np.testing.assert_array_equal(order, lone)  # all alike: the first left goes first


def test_crowd_bench_frame_reports_period_and_latency(tmp_path):
    from bench.cli import main

    out = tmp_path / "frame.json"
    # The horde around the survivor from the start: 20 agents outside the 25 m clear disc would stand in
    # the world's corners, which the overview does not frame whole.
    scene = tmp_path / "bench.toml"
    scene.write_text("[ai]\nstart_clear = 0.0\n")
    assert main(["frame", "--scene", str(scene), "--agents", "0,20", "--frames", "3", "--repeats", "2", "--warmup", "1", "--size", "64x36",
                 "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert [r["agents"] for r in report["rows"]] == [0, 20] and report["device"]
    for row in report["rows"]:
        assert len(row["periods_ms"]) == 2 and row["period_ms"] > 0 and row["latency_ms"] > 0
    assert "draw" in report["rows"][1]["passes_ms"] and "draw" in report["rows"][0]["passes_ms"]  # the survivor, at 0 too
    row = report["rows"][1]
    assert row["cull"] == "gpu" and row["drawn"]["visible"] == 21 and row["drawn"]["triangles"] > 0  # 20 zombies and the survivor
    assert set(row["frame_period_ms"]) == {"p50", "p95", "max"} and row["gpu_bytes"]["cull"] > 0
    assert row["weapons"]["weapons"] >= row["weapons"]["drawn"] >= 0  # placed, and drawn of them
    assert main(["frame", "--size", "1x1"]) == 2  # a bad size: one line, exit 2


def test_paced_frames_run_at_most_two_ahead_and_time_each_start(gl_context, monkeypatch):
    """The period loop waits for frame k - 2's fence before issuing frame k (as a double-buffered swap
    does), never for the frame just issued, and returns one interval per frame."""
    from crowd import smoke

    events = []

    class Recorded:
        def __init__(self):
            self.k = len([e for e in events if e[0] == "fence"])
            events.append(("fence", self.k))

        def wait(self):
            events.append(("wait", self.k))

        def release(self):
            pass

    monkeypatch.setattr(smoke, "Fence", Recorded)
    intervals = smoke.paced_frames(gl_context, lambda: events.append(("frame", None)), 5)
    assert len(intervals) == 5 and all(ms >= 0 for ms in intervals)
    waits = [k for kind, k in events if kind == "wait"]
    assert waits == [0, 1, 2]  # before frames 2, 3 and 4: for frames 0, 1 and 2
    order = [kind for kind, _ in events]
    assert order[:4] == ["frame", "fence", "frame", "fence"] and order[4] == "wait"


def test_runs_are_quiet(tmp_path):
    """No deprecation warning on import of anything the demo, the window or the benchmarks load (the
    only one was moderngl-window's "import glm", filtered at its import in crowd.gl), no third-party INFO
    line, and a headless run without weapons drawn says so instead of "None mm"."""
    imports = subprocess.run([sys.executable, "-W", "error::DeprecationWarning", "-W", "error::PendingDeprecationWarning", "-c",
                              "import app.demo, app.window, bench.cli, bench.plots, crowd.pipeline"], cwd=ROOT, capture_output=True, text=True,
                             timeout=300)
    assert imports.returncode == 0, imports.stderr[-2000:]
    out = subprocess.run([sys.executable, "-W", "always", "-m", "app.demo", "--headless", "--frames", "3", "--agents", "6", "--size", "96x54",
                          "--armed-share", "1", "--screenshot", str(tmp_path / "q.png")], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stderr == "", out.stderr[-2000:]
    assert " - INFO - " not in out.stdout and "None mm" not in out.stdout
    assert "frames x their simulated frame time" in out.stdout
    empty = subprocess.run([sys.executable, "-m", "app.demo", "--headless", "--frames", "2", "--agents", "0", "--size", "96x54",
                            "--screenshot", str(tmp_path / "e.png")], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert empty.returncode == 0 and "no weapon drawn" in empty.stdout and "None" not in empty.stdout, empty.stdout


@pytest.mark.parametrize("agents", [200, 2_000, 20_000, 100_000])
def test_the_default_picture_shows_the_horde_at_any_size(gl_context, agents):
    """Issue 22, point 4: the default camera frames the whole of a small crowd, and the player and the
    horde around it in a big one, so the agents cover a share of the picture that does not fall away
    with the crowd's size (the whole-crowd view had 1.6 % at 100,000 agents, and less beyond)."""
    from crowd.gl import Offscreen
    from crowd.pipeline import CrowdPipeline
    from crowd.pipeline_config import PipelineConfig

    size = (320, 180)
    with Offscreen(gl_context, size) as target, CrowdPipeline(gl_context, PipelineConfig(agents=agents, cull="cpu", weapons=False)) as p:
        p.camera = p.default_camera(size[0] / size[1])
        for _ in range(2):
            p.frame(target.framebuffer, 1 / 30)
        crowd = target.image().astype(int)
        p.set("agents", 0)  # the same camera on the same ground, nobody on it
        p.frame(target.framebuffer, 1 / 30)
        empty = target.image().astype(int)
    covered = float(np.mean(np.abs(crowd - empty).max(axis=2) > 8))
    assert covered > 0.08, f"{agents:,} agents cover {covered:.1%} of the default picture"
