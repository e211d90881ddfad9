"""Issue 7: the shell error measure, the stiff and extreme cases, and `crowd-bench error` end to end
(small, on llvmpipe: the H100's numbers are in docs/BENCHMARKS.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench import stability
from crowd.anim import accuracy
from crowd.transforms import trs_to_mat4
from crowd.anim.bake import bake
from bench.cli import main as bench_main
from bench.error_report import pareto_front, rank_candidates
from crowd.frame import CLIP, WEIGHT, empty_layers


def test_shell_error_of_a_known_rotation_and_translation(zombie):
    """1 mrad about a joint's axis moves its 3 cm shell points by up to 0.03 mm; 2 mm of translation by 2 mm."""
    sk = zombie.skeleton
    layers = empty_layers(1, 1)
    layers[0, 0, WEIGHT] = 1.0
    truth = accuracy.truth(sk, zombie.clips, layers)
    points = accuracy.shell_points(sk)
    assert points.shape == (sk.joint_count, 6, 4)
    bind = np.linalg.inv(sk.inverse_bind)
    np.testing.assert_allclose(np.linalg.norm(points[..., :3] - bind[:, None, :3, 3], axis=-1), accuracy.SHELL_M)
    moved = truth.copy()
    moved[..., :3, 3] += [0.002, 0.0, 0.0]
    np.testing.assert_allclose(accuracy.shell_error(moved, truth, points), 0.002, rtol=1e-9)
    j = sk.index("head")
    turn = np.eye(4)
    turn[:3, :3] = trs_to_mat4(np.zeros(3), np.array([np.sin(5e-4), 0, 0, np.cos(5e-4)]), np.ones(3))[:3, :3]
    pivot = (truth[0, j] @ bind[j])[:3, 3]  # where the joint is in this pose
    about_joint = np.eye(4)
    about_joint[:3, 3] = pivot
    inv_pivot = np.eye(4)
    inv_pivot[:3, 3] = -pivot
    turned = truth.copy()
    turned[0, j] = about_joint @ turn @ inv_pivot @ truth[0, j]
    err = accuracy.shell_error(turned, truth, points)[0, j]
    assert err.max() <= 0.03e-3 * 1.0000001 and err.max() > 0.029e-3


def test_samples_cover_every_clip_alone_and_blends_of_two_to_four(zombie):
    s = accuracy.draw_samples(zombie.clips, np.random.default_rng(0), 5, 100)
    c = len(zombie.clips)
    assert s.layers.shape == (5 * c + 100, 4, 4) and s.single.sum() == 5 * c
    assert sorted(set(s.layers[s.single, 0, CLIP].astype(int))) == list(range(c))
    active = (s.layers[~s.single, :, WEIGHT] > 0).sum(axis=1)
    assert active.min() == 2 and active.max() == 4


def test_gpu_error_of_the_default_is_under_a_millimetre_and_dq_blends_are_not(gl_context, zombie):
    """The measurement behind the default: qt_lerp at 30 fps stays under 1 mm against the source clips
    on every clip and blend; dq_lerp's dual-quaternion blend of the hips is off by centimetres."""
    clips = list(zombie.clips)
    s = accuracy.draw_samples(clips, np.random.default_rng(4), 30, 300)
    truth = accuracy.truth(zombie.skeleton, clips, s.layers)
    baked = bake(zombie.skeleton, clips, 30, "f32")
    default = accuracy.measure_gpu(gl_context, zombie.skeleton, baked, s.layers, truth, "qt_lerp")
    assert default.max() < 1e-3
    dq = accuracy.measure_gpu(gl_context, zombie.skeleton, baked, s.layers, truth, "dq_lerp")
    assert dq[s.single].max() < 1e-3 and dq[~s.single].max() > 0.05


def test_stability_cases_pass_with_the_default(gl_context, zombie):
    cases = stability.run_cases(gl_context, zombie, "qt_corrected", 30.0, "f32", hours=0.25)
    assert [c["case"] for c in cases] == ["antipodal blends", "equal-weight opposite rotations", "64-joint chains", "256-joint chains",
                                          "keys up to a half turn apart", "joint scale 1e-4 and 1e4", "phase near 1.0",
                                          "clip time after 0.25 hours of play", "dt spikes"]
    for c in cases:
        assert c["passed"], c
        assert 0.0 <= c["max_error_mm"] <= c["bound_mm"]


def test_plain_nlerp_fails_keys_a_half_turn_apart(gl_context):
    """The half-turn case's bound is qt_corrected's: plain nlerp is 0.14 rad off between keys that far apart."""
    case = stability.half_turn_keys(gl_context, "qt_lerp", 30.0, "f32")
    assert not case["passed"] and case["max_error_mm"] > 50.0


def test_stability_cases_catch_f16_on_long_chains(gl_context):
    """The bounds are not for show: f16 keys quantise each of 64 joints' rotations, which adds up to
    millimetres at the tip of a 3.2 m chain."""
    case = stability.long_chains(gl_context, "qt_lerp", 30.0, "f16")
    assert not case["passed"] and case["max_error_mm"] > case["bound_mm"]


def _row(err, ms, nbytes, fps=30.0):
    return {"max_error_mm": err, "zombie_max_error_mm": err, "gpu_ms_100k": ms, "bytes": nbytes, "bake_fps": fps}


def test_pareto_front_and_default_ranking():
    rows = [_row(0.4, 1.00, 100), _row(0.05, 1.05, 200), _row(5.0, 0.80, 100), _row(0.4, 1.004, 100, "source"),
            _row(2.0, 1.2, 300), _row(0.9, 1.0, 50)]
    front = pareto_front(rows, tie=0.01)
    assert 4 not in front  # slower, larger and less accurate than row 0
    assert {0, 1, 2, 3, 5} <= set(front)
    # Row 5 is as fast and smaller, but row 0 ties with it on time, so bytes decide: 5, then 0 before
    # its "source" twin, then the slower, more accurate row 1. Row 2 misses a 1 mm target.
    assert rank_candidates(rows, front, tie=0.01, target_mm=1.0) == [5, 0, 3, 1]
    assert rank_candidates(rows, front, tie=0.01) == [1]  # the report's own target: 0.1 mm, ACL's bar


def test_crowd_bench_error_end_to_end(tmp_path, gl_context, capsys):
    out = tmp_path / "error.json"
    plot = tmp_path / "error.png"
    rc = bench_main(["error", "--rates", "15,source", "--storage", "f32", "--interpolations", "qt_lerp,qt_corrected", "--per-clip", "4",
                     "--blends", "40", "--cost-agents", "50,200", "--repeats", "2", "--hours", "0.05", "--json", str(out), "--plot", str(plot)])
    assert rc == 0
    report = json.loads(out.read_text())
    assert set(report) >= {"device", "rows", "stability"}
    keys = {"bake_fps", "storage", "interpolation", "max_error_mm", "p99_error_mm", "share_under_1mm", "share_under_0_1mm",
            "gpu_ms_10k", "gpu_ms_100k",
            "bytes", "default"}
    assert len(report["rows"]) == 4 and all(keys <= set(r) for r in report["rows"])
    defaults = [r for r in report["rows"] if r["default"]]
    # The default is the cheapest on the front within 0.1 mm (ACL's bar): only qt_corrected gets there.
    assert len(defaults) == 1 and defaults[0]["interpolation"] == "qt_corrected" and defaults[0]["max_error_mm"] < 0.1
    assert len(report["stability"]) == 9 and all({"case", "max_error_mm", "bound_mm", "passed"} <= set(c) for c in report["stability"])
    # The maximum is searched for, not sampled: with 4 random phases a clip the source-rate qt_lerp row
    # still has the attack's 0.485 mm at hand_r_socket (the 1,201-phase grid of the old report saw 0.39 mm).
    (plain,) = [r for r in report["rows"] if r["interpolation"] == "qt_lerp" and r["bake_fps"] == "source"]
    attack = plain["models"]["zombie"]["per_clip_worst"]["attack"]
    assert attack["joint"] == "hand_r_socket" and 0.48 < attack["max_error_mm"] < 0.49 and 0.40 < attack["phase"] < 0.42
    assert plain["worst"]["clip"] == "attack" and plain["max_error_mm"] == pytest.approx(attack["max_error_mm"])
    for row in report["rows"]:
        assert row["max_error_mm"] >= max(row["models"]["zombie"]["per_clip_max_mm"].values()) - 1e-3
        assert {"model", "clip", "joint", "max_error_mm"} <= set(row["worst"])
    from PIL import Image

    image = np.asarray(Image.open(plot).convert("RGB"))
    assert image.shape == (1000, 1600, 3) and len(np.unique(image.reshape(-1, 3), axis=0)) > 50  # drawn, not blank
    out = capsys.readouterr().out
    assert "default" in out and "max at" in out and "zombie: attack @ 0.41" in out and "hand_r_socket" in out
    if not report["gpu_ms_measured"]:  # llvmpipe: its timer queries answer 0, and the report says so instead of 0.0 ms
        assert all(r["gpu_ms_100k"] is None for r in report["rows"]) and "GPU ms not measured here" in out


def test_crowd_bench_error_quick_runs_the_default_and_the_stability_cases(tmp_path, gl_context, capsys):
    out = tmp_path / "quick.json"
    assert bench_main(["error", "--quick", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    row, packed = report["rows"]
    assert (row["bake_fps"], row["storage"], row["interpolation"]) == (30.0, "f32", "qt_corrected") and row["default"]
    assert len(report["stability"]) == 9 and all(c["passed"] for c in report["stability"])
    # ACL's bar: 0.1 mm on the 3 cm shell, searched for; qt_lerp's nlerp had 0.485 mm at the attack's hand_r_socket.
    assert row["max_error_mm"] < 0.1 and all(v < 0.1 for v in row["models"]["zombie"]["per_clip_max_mm"].values())
    # The compressed bake at its default bound, with its own stiff cases (bounds raised by 0.5 mm).
    assert packed["storage"] == "compressed@0.5" and not packed["default"] and packed["compression"]["ratio"] >= 8.0
    assert packed["max_error_mm"] <= 0.5 and packed["bytes"] * 8 < row["bytes"]
    assert len(packed["stability"]) == 9 and all(c["passed"] for c in packed["stability"])
    assert all("raised by the compression bound, 0.5 mm" in c["detail"] for c in packed["stability"])


def test_crowd_bench_error_refuses_unknown_interpolations(capsys):
    with pytest.raises(SystemExit, match="unknown interpolation 'slerp'"):
        bench_main(["error", "--interpolations", "slerp"])


def test_the_search_finds_a_narrow_peak_between_seeds(zombie):
    """A made-up error: a broad bump of 0.5 mm and a peak of 1 mm a third as wide as the seed spacing
    (0.0035 of a cycle on the attack), centred between two seeds (which see an eighth of it). The
    search must come back with the peak, its phase within a tenth of the peak's width, and the maximum
    within the 1 % tolerance."""
    sk = zombie.skeleton
    clips = [zombie.clip("attack")]
    search = accuracy.ClipMaxima(sk, clips)
    seeds = np.unique(search.seed_layers[:, 0, 1])
    peak = (float(seeds[80]) + float(seeds[81])) / 2

    def made_up(phase):
        return 0.5e-3 * np.exp(-((phase - 0.7) / 0.05) ** 2) + 1e-3 * np.exp(-((phase - peak) / 1.2e-3) ** 2)

    def palette_of(layers):
        pal = accuracy.truth(sk, clips, layers)[:, :, :3, :].copy()
        pal[:, :, 0, 3] += made_up(layers[:, 0, 1].astype(np.float64))[:, None]  # every joint shifted along x
        return pal

    assert made_up(seeds).max() < 0.51e-3 and made_up(seeds[80]) < 0.15e-3  # the seeds miss the peak
    found = search.find(palette_of)[0]
    assert found.error_m == pytest.approx(1e-3, rel=0.01) and abs(found.phase - peak) < 1.2e-4
    assert found.rounds >= 2 and found.poses < len(seeds) + 20 * 4 * 16


def test_the_search_matches_a_dense_scan_on_the_gpu(gl_context, zombie):
    """The attack alone at 30 fps, qt_lerp: the search's maximum against 20,001 evenly spaced phases."""
    clips = [zombie.clip("attack")]
    baked = bake(zombie.skeleton, clips, 30, "f32")
    search = accuracy.ClipMaxima(zombie.skeleton, clips)
    with accuracy.gpu_palettes(gl_context, baked, 1, "qt_lerp") as palette_of:
        found = search.find(palette_of)[0]
        dense = accuracy.single_clip_layers(np.zeros(20001, int), np.linspace(0.0, 1.0, 20001))
        errors = accuracy.shell_error(palette_of(dense), accuracy.truth(zombie.skeleton, clips, dense), search.points).max(axis=(1, 2))
    assert found.error_m >= 0.99 * errors.max() and found.error_m < 1.01 * errors.max()
    assert zombie.skeleton.names[found.joint] == "hand_r_socket" and found.poses < 2000


@pytest.mark.parametrize("content, words", [(None, "cannot read it"), (b"\x89PNG\r\n", "not JSON"), (b"{\"rows\": [", "not JSON"),
                                            (b"[1, 2]", "a JSON list"), (b"{}", "no rows"),
                                            (b'{"rows": [{"max_error_mm": "big", "gpu_ms_100k": 1}]}', "row 0: max_error_mm"),
                                            (b'{"rows": [{"max_error_mm": 1, "gpu_ms_100k": 1, "interpolation": "qt_lerp", "storage": "f32", "bake_fps": [30]}]}',
                                             "row 0: bake_fps")])
def test_plot_error_refuses_what_is_not_a_report_in_one_line(tmp_path, capsys, content, words):
    report = tmp_path / "report.json"
    if content is not None:
        report.write_bytes(content)
    rc = bench_main(["plot-error", str(report), str(tmp_path / "plot.png")])
    err = capsys.readouterr().err
    assert rc == 2 and words in err and err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"crowd-bench plot-error: {report}: ") and not (tmp_path / "plot.png").exists()
