"""crowd-bench peers: the crowd against Panda3D Actors. The Panda3D side needs the optional extra
(pip install '.[peers]'); its tests skip without it, and the command then measures the crowd alone."""

import json
import subprocess
import sys

import numpy as np
import pytest

from bench import peer_work, peers
from bench.cli import main as bench_main


def _result(system, mode, points):
    return {"system": system, "mode": mode, "rows": [{"agents": a, "frame_ms": ms, "cpu_ms": ms} for a, ms in points]}


def test_sustained_counts_and_ratios_take_the_faster_peer():
    results = [
        _result("crowd", "walk", [(16, 1.0), (4096, 16.0), (5000, 17.0), (8192, 32.0), (16384, 64.0)]),
        _result("panda3d", "cpu_walk", [(16, 4.0), (64, 16.0), (128, 33.0)]),
        _result("panda3d", "gpu_walk", [(16, 1.3), (256, 15.0), (512, 36.0)]),
    ]
    summary = peers.summarise(results)
    got = {(s["system"], s["mode"], s["budget_ms"]): s["agents"] for s in summary["sustained"]}
    assert got[("crowd", "walk", 16.7)] == 4096
    assert got[("crowd", "walk", 33.3)] == 8192
    assert got[("panda3d", "cpu_walk", 33.3)] == 128
    assert got[("panda3d", "gpu_walk", 33.3)] == 256
    ratio = next(r for r in summary["ratios"] if r["crowd_mode"] == "walk" and r["budget_ms"] == 16.7)
    assert ratio["panda3d_mode"] == "gpu_walk" and ratio["panda3d_agents"] == 256 and ratio["ratio"] == 16.0
    # A mode that cannot hold even the first count sustains 0, and its ratio is left undefined.
    none = peers.summarise([_result("crowd", "walk", [(16, 50.0)]), _result("panda3d", "gpu_walk", [(16, 40.0)])])
    assert {s["agents"] for s in none["sustained"]} == {0}
    assert all(r["ratio"] is None for r in none["ratios"])


def test_layout_is_the_same_for_both_sides_and_every_count():
    a = peer_work.agent_layout(100, seed=3)
    b = peer_work.agent_layout(100, seed=3)
    for x, y in zip(a[:4], b[:4]):
        assert np.array_equal(x, y)
    pos, yaw, phase, weight, (eye, target, far) = a
    assert pos.shape == (100, 3) and np.all((phase >= 0) & (phase < 1))
    assert np.all((weight >= peer_work.WEIGHT_RANGE[0]) & (weight <= peer_work.WEIGHT_RANGE[1]))
    assert far > np.linalg.norm(eye - target)


def test_panda_ready_gltf_anchors_the_skin_at_the_root_joints_parent(tmp_path):
    """The copy Panda3D loads differs in the skin: the root joint's parent joins the joint list (so
    panda3d-gltf puts the Character there) with its inverse world matrix; and in its morph targets, left
    out (next test); nothing else changes."""
    import pygltflib

    from bench.peers_panda import panda_ready_gltf
    from crowd.asset.zombie import ASSET_PATH

    target = tmp_path / "ready.glb"
    panda_ready_gltf(ASSET_PATH, target)
    before, after = pygltflib.GLTF2().load(str(ASSET_PATH)), pygltflib.GLTF2().load(str(target))
    old, new = before.skins[0], after.skins[0]
    names = [n.name for n in after.nodes]
    assert new.joints[:-1] == old.joints and names[new.joints[-1]] == "zombie"

    def matrices(g, skin):
        acc = g.accessors[skin.inverseBindMatrices]
        view = g.bufferViews[acc.bufferView]
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        return np.frombuffer(g.binary_blob()[start:start + acc.count * 64], np.float32).reshape(-1, 4, 4)

    assert np.array_equal(matrices(after, new)[:-1], matrices(before, old))
    assert np.allclose(matrices(after, new)[-1], np.eye(4))  # the zombie node sits at the origin
    assert len(after.meshes) == len(before.meshes) and len(after.animations) == len(before.animations)
    assert [n.name for n in before.nodes] == names
    # One scene only: panda3d-gltf would skin a mesh that two scenes show to the last scene's Character.
    assert len(after.scenes) == 1 and after.scenes[0].nodes == before.scenes[before.scene or 0].nodes


@pytest.mark.parametrize("lod", [0, 1, 2])
def test_panda_ready_gltf_is_dense_and_without_morph_targets(tmp_path, lod):
    """What panda3d-gltf 1.3 reads (without Panda3D, so it runs everywhere): every accessor dense, with a
    bufferView; no targets, mesh weights or weight channels (the zombie's morph targets are sparse
    accessors without one, which stopped its converter with KeyError 'bufferView')."""
    import pygltflib

    from bench.peers_panda import panda_ready_gltf
    from crowd.asset.zombie import ASSET_PATH

    before = pygltflib.GLTF2().load(str(ASSET_PATH))
    assert any(a.sparse is not None and a.bufferView is None for a in before.accessors)  # what broke it
    panda_ready_gltf(ASSET_PATH, tmp_path / "ready.glb", lod=lod)
    after = pygltflib.GLTF2().load(str(tmp_path / "ready.glb"))
    assert all(a.sparse is None and a.bufferView is not None for a in after.accessors)
    assert all(not m.weights and all(not p.targets for p in m.primitives) for m in after.meshes)
    assert all("targetNames" not in (m.extras or {}) for m in after.meshes)
    assert all(c.target.path != "weights" for a in after.animations for c in a.channels)
    kept = [(a.name, len([c for c in a.channels if c.target.path != "weights"])) for a in before.animations]
    assert [(a.name, len(a.channels)) for a in after.animations] == kept


def test_panda_ready_gltf_writes_a_sparse_attribute_dense(tmp_path):
    """A file whose positions are a sparse accessor over zeros: the copy's dense positions are the ones
    the importer reads from the original."""
    import pygltflib

    from bench.peers_panda import panda_ready_gltf
    from crowd.asset.gltf import load_character
    from tests.gltf_factory import make_gltf

    source = make_gltf(tmp_path, sparse=True)
    panda_ready_gltf(source, tmp_path / "ready.glb")
    after = pygltflib.GLTF2().load(str(tmp_path / "ready.glb"))
    assert all(a.sparse is None and a.bufferView is not None for a in after.accessors)
    a, b = load_character(source), load_character(tmp_path / "ready.glb")
    assert [m.positions.tobytes() for m in a.meshes] == [m.positions.tobytes() for m in b.meshes]


def test_panda_ready_gltf_shows_the_asked_lod_in_place_of_lod0(tmp_path):
    import pygltflib

    from bench.peers_panda import lod_levels, panda_ready_gltf
    from crowd.asset.zombie import ASSET_PATH

    assert lod_levels(ASSET_PATH) == [0, 1, 2]  # LOD3 merges the pieces into one mesh: not every piece has one
    panda_ready_gltf(ASSET_PATH, tmp_path / "lod1.glb", lod=1)
    after = pygltflib.GLTF2().load(str(tmp_path / "lod1.glb"))
    shown = [after.nodes[i].name for i in after.scenes[0].nodes]
    assert shown == ["zombie", "zombie_body_lod1", "zombie_head_a_lod1", "zombie_shirt_torn_lod1"]
    with pytest.raises(ValueError, match="no complete LOD 3; its levels are \\[0, 1, 2\\]"):
        panda_ready_gltf(ASSET_PATH, tmp_path / "lod3.glb", lod=3)


def test_crowd_side_measures_and_its_bind_pose_is_told_apart(tmp_path, gl_context):
    spec = {"system": "crowd", "mode": "walk", "model": None, "clips": ["shamble", "run"], "size": [320, 180], "seed": 1,
            "frames": 2, "warmup": 1, "start": 16, "max_agents": 32, "limit_ms": 1e9, "budgets": [1e9], "refine": 0,
            "screenshot": str(tmp_path / "crowd_walk.png"), "bind_screenshot": str(tmp_path / "crowd_bind.png")}
    side = peers.CrowdSide(spec)
    try:
        result = peers.measure(side, spec)
    finally:
        side.release()
    assert [r["agents"] for r in result["rows"]] == [16, 32]
    for row in result["rows"]:
        assert row["frame_ms"] > 0 and row["cpu_ms"] >= 0 and row["visible"] == row["agents"]
    walk, bind = peers._mask(tmp_path / "crowd_walk.png"), peers._mask(tmp_path / "crowd_bind.png")
    assert walk.sum() > 500 and bind.sum() > 500  # both drew the crowd
    assert peers._iou(walk, bind) < peers.POSE_IOU_MIN  # a bind-pose peer would fail the pose check


def _run_cli(tmp_path, *extra):
    out = tmp_path / "peers.json"
    code = bench_main(["peers", "--size", "320x180", "--frames", "2", "--warmup", "1", "--limit-ms", "0", "--refine", "0",
                       "--screenshots", str(tmp_path / "shots"), "--json", str(out), *extra])
    return code, (json.loads(out.read_text()) if out.exists() else None)


def test_peers_without_panda3d_measures_the_crowd_and_says_why(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(peers, "panda3d_missing", lambda: "panda3d not installed (pip install '.[peers]')")
    code, report = _run_cli(tmp_path, "--modes", "walk")
    assert code == 0
    assert "skipping the Panda3D side: panda3d not installed (pip install '.[peers]')" in capsys.readouterr().out
    assert report["device"] and report["notes"]
    assert {(r["system"], r["mode"]) for r in report["rows"]} == {("crowd", "walk")}
    for row in report["rows"]:
        assert {"system", "mode", "agents", "frame_ms", "cpu_ms"} <= set(row)
    for s in report["sustained"]:
        assert {"system", "mode", "budget_ms", "agents"} <= set(s)


@pytest.mark.parametrize("argv, message", [
    (["--size", "0x0"], "size must be WxH with each side 16 to 8192"),
    (["--systems", "unity"], "systems are crowd and panda3d"),
    (["--systems", "none", "--merge", "missing.json"], "--merge missing.json"),
])
def test_peers_refuses_bad_input_in_one_line(tmp_path, capsys, argv, message):
    assert bench_main(["peers", "--screenshots", str(tmp_path), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def test_panda3d_actors_are_measured_and_pass_the_pose_check(tmp_path):
    if peers.panda3d_missing():
        pytest.skip(f"the Panda3D side needs the optional extra: {peers.panda3d_missing()}")
    code, report = _run_cli(tmp_path, "--modes", "walk,gpu_walk,cpu_walk,gpu_walk_threaded")
    assert code == 0, report.get("errors")
    panda_modes = ("gpu_walk", "cpu_walk", "gpu_walk_threaded")
    assert {(r["system"], r["mode"]) for r in report["rows"]} == {("crowd", "walk"), *(("panda3d", m) for m in panda_modes)}
    checks = {c["mode"]: c for c in report["pose_check"]}
    for mode in panda_modes:  # drawn posed: close to the crowd's silhouette, far from the bind pose's
        assert checks[mode]["ok"] and checks[mode]["iou"] > checks[mode]["bind_pose_iou"] + 0.2
    info = {r["mode"]: r["info"] for r in report["results"]}
    assert info["gpu_walk"]["pipe"] == "eglGraphicsPipe" and info["gpu_walk"]["triangles_per_agent"] > 0
    # Threaded, the draw thread's context must be desktop GL, not EGL's default OpenGL ES 1.1.
    assert "OpenGL ES" not in info["gpu_walk_threaded"]["gl"]


def test_every_panda3d_mode_has_a_pose_reference_a_plot_style_and_a_peer_setting():
    from bench.peers_panda import HARDWARE
    from bench.plots import PEER_STYLE

    panda_modes = {mode for system, mode in peers.MODES if system == "panda3d"}
    assert panda_modes == set(peers.POSE_REFERENCE) == set(HARDWARE)
    assert set(peers.POSE_REFERENCE.values()) <= {mode for system, mode in peers.MODES if system == "crowd"}
    assert set(peers.MODES) <= set(PEER_STYLE)
    paired = {m for _, modes in peers.PAIRS for m in modes}
    assert paired == panda_modes


def test_panda3d_lod_actor_shows_the_level_the_crowd_would_at_each_distance(tmp_path):
    """One Actor built with setLODNode / addLOD; the camera at 8, 20 and 60 m from its LOD centre; each
    level drawn alone in turn: only the level the crowd's LOD distances pick draws anything (at 480x270:
    at 60 m the zombie is 10 px tall; at 160x90 its LOD2 covered no whole pixel). Panda3D
    runs in a child process, as in the benchmark: its GL stack would leave this process's contexts
    without a current one."""
    if peers.panda3d_missing():
        pytest.skip(f"the Panda3D side needs the optional extra: {peers.panda3d_missing()}")
    from crowd.asset.gltf import load_character

    character = load_character(None)
    heads = sorted({m.piece for m in character.meshes if m.group == "head"})
    drawn = [m for m in character.meshes if not m.group or m.piece == heads[0]]  # what the glTF scene shows
    expected = [sum(m.triangle_count for m in drawn if m.lod == level) for level in range(3)]
    script = tmp_path / "probe.py"
    script.write_text(_LOD_PROBE)
    proc = subprocess.run([sys.executable, str(script), str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["triangles_per_level"] == expected and expected[0] > expected[1] > expected[2]
    for distance, level in ((8.0, 0), (20.0, 1), (60.0, 2)):
        shows = result["shows"][str(distance)]
        assert shows == [level], f"at {distance} m Panda3D showed levels {shows}, the crowd would show {level}"


_LOD_PROBE = """
import json, sys
from pathlib import Path
from bench import peers
from bench.peers_panda import PandaSide
from crowd.asset.zombie import ASSET_PATH

out = Path(sys.argv[1])
spec = {"system": "panda3d", "mode": "gpu_walk_lod", "model": str(ASSET_PATH), "clips": ["shamble", "run"],
        "size": [480, 270], "seed": 1, "lod_distances": [14.0, 40.0, 90.0]}
side = PandaSide(spec)
side.set_agents(1)
actor = side.actors[0]
actor.setPos(0, 0, 0)
center = side.lod_center
side.lens.setNearFar(0.1, 200.0)
result = {"triangles_per_level": side.triangles_per_level, "shows": {}}
for distance in (8.0, 20.0, 60.0):
    side.base.cam.setPos(center[0], center[1] - distance, center[2])
    side.base.cam.lookAt(center)
    shows = []
    for only in range(3):
        for k in range(3):
            (actor.getLOD(str(k)).show if k == only else actor.getLOD(str(k)).hide)()
        side.work()
        side.finish()
        side.save_screenshot(str(out / "lod.png"))
        if peers._mask(out / "lod.png").sum() > 0:
            shows.append(only)
    result["shows"][str(distance)] = shows
side.release()
print(json.dumps(result))
"""


def test_a_pose_check_without_the_crowds_screenshot_says_so_and_passes_nothing(tmp_path):
    from PIL import Image

    shot = tmp_path / "panda3d_gpu_walk_lod.png"
    Image.new("RGB", (32, 32)).save(shot)
    checks = peers.pose_checks([{"system": "panda3d", "mode": "gpu_walk_lod", "screenshot": str(shot), "rows": []}], tmp_path)
    assert len(checks) == 1 and checks[0]["ok"] is None and checks[0]["iou"] is None
    assert checks[0]["against"] == "crowd_walk_lod.png" and "not checked: no crowd_walk_lod.png" in checks[0]["why"]
