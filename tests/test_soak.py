"""The soak, short: the game as shipped (the mixed horde in the town, the scripted survivor through its
rounds) headless; after the warm-up its resident memory and live GL objects stay within 2 % and no
fault is logged. ``crowd-bench soak`` runs the issue's 20,000 frames at 10,000 agents (docs/BENCHMARKS.md)."""

from __future__ import annotations

import pytest

from bench.cli import main
from bench.soak import SoakError, run_soak


def test_a_short_soak_holds_memory_and_gl_objects_and_logs_no_fault(gl_context, tmp_path):
    # The warm-up covers the first rounds: on llvmpipe the memory settles over its first 300 frames or so
    # (from frame 100 to 420 it rose 2.6 %; from 320 to 640 it moved -0.6 and +0.03 % in two runs).
    # Short rounds, so that several new crowds come and go within the 640 frames: the horde starts
    # around the survivor and the pressure does not build (a newcomer's round lasts a minute).
    scene = tmp_path / "soak.toml"
    scene.write_text("[ai]\nstart_clear = 0.0\nalert_rate = 0.0\n")
    result = run_soak(agents=300, frames=640, size=(96, 54), warmup=320, every=20, scene_path=scene)
    assert result["faults"] == []
    assert len(result["samples"]) == 17 and result["samples"][-1]["agents"] == 300 and result["rounds"] >= 3
    # A leak grows: memory may fall back past the warm-up (glibc handing freed frames back to the system:
    # -3.6 % and -6.3 % in two runs once meshes merged and the cull's lists shrank) but may not rise. The
    # resident memory swings between two levels on llvmpipe (bench.soak says so), so the floor and ceiling
    # of the samples are what may not rise, not their quartiles' medians (-5.9 % and +3.8 % on one tree).
    assert result["rss_mb"]["growth"] <= 0.02, result["rss_mb"]
    assert result["gl_objects"]["spread"] <= 0.02, result["gl_objects"]


def test_the_soak_refuses_settings_it_cannot_run_in_one_line(tmp_path, capsys):
    with pytest.raises(SoakError, match="warmup"):
        run_soak(agents=10, frames=10, size=(16, 16), warmup=10, every=5)
    for argv in (["soak", "--warmup", "0"], ["soak", "--every", "0"], ["soak", "--agents", "-5"],
                 ["soak", "--scene", str(tmp_path / "missing.toml")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("crowd-bench: ") and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
