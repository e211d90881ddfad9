"""crowd-bench peers: the crowd against Panda3D Actors. The Panda3D side needs the optional extra
(pip install '.[peers]'); its tests skip without it, and the command then measures the crowd alone."""

import json

import numpy as np
import pytest

from crowd import peers
from crowd.bench import main as bench_main


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
    a = peers.agent_layout(100, seed=3)
    b = peers.agent_layout(100, seed=3)
    for x, y in zip(a[:4], b[:4]):
        assert np.array_equal(x, y)
    pos, yaw, phase, weight, (eye, target, far) = a
    assert pos.shape == (100, 3) and np.all((phase >= 0) & (phase < 1))
    assert np.all((weight >= peers.WEIGHT_RANGE[0]) & (weight <= peers.WEIGHT_RANGE[1]))
    assert far > np.linalg.norm(eye - target)


def test_panda_ready_gltf_anchors_the_skin_at_the_root_joints_parent(tmp_path):
    """The copy Panda3D loads differs only in the skin: the root joint's parent joins the joint list
    (so panda3d-gltf puts the Character there) with its inverse world matrix; nothing else changes."""
    import pygltflib

    from crowd.peers_panda import panda_ready_gltf
    from crowd.zombie import ASSET_PATH

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
    code, report = _run_cli(tmp_path, "--modes", "walk,gpu_walk,cpu_walk")
    assert code == 0, report.get("errors")
    assert {(r["system"], r["mode"]) for r in report["rows"]} == {("crowd", "walk"), ("panda3d", "gpu_walk"), ("panda3d", "cpu_walk")}
    checks = {c["mode"]: c for c in report["pose_check"]}
    for mode in ("gpu_walk", "cpu_walk"):  # drawn posed: close to the crowd's silhouette, far from the bind pose's
        assert checks[mode]["ok"] and checks[mode]["iou"] > checks[mode]["bind_pose_iou"] + 0.2
    info = next(r["info"] for r in report["results"] if r["mode"] == "gpu_walk")
    assert info["pipe"] == "eglGraphicsPipe" and info["triangles_per_agent"] > 0
