"""Scene files: loading, validation with one-line errors, atomic saving with a backup, and scenes that
use only what they ask for."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys

import pytest

from crowd.pipeline_config import PipelineConfig
from crowd.resources import SCENE_DIR
from crowd.scene import CharacterEntry, Scene, SceneError, load_scene, save_scene
from crowd.smoke import run_headless
from conftest import ROOT

SIZE = (160, 90)


def test_shipped_scenes_load_and_the_horde_is_the_default():
    names = sorted(p.name for p in SCENE_DIR.glob("*.toml"))
    assert names == ["dense_horde.toml", "horde.toml", "stress_10k.toml", "unarmed_small.toml"]
    horde = load_scene(SCENE_DIR / "horde.toml")
    assert horde.pipeline_config() == Scene().pipeline_config()  # the CLI without --scene runs the same crowd
    assert [c.model for c in horde.characters] == ["zombie", "brute"]  # a mixed horde
    stress = load_scene(SCENE_DIR / "stress_10k.toml")
    assert stress.agents == 10_000 and stress.weapons
    small = load_scene(SCENE_DIR / "unarmed_small.toml")
    assert small.agents == 24 and not small.weapons and small.camera is not None and small.ai.half_extent == 10.0
    dense = load_scene(SCENE_DIR / "dense_horde.toml")
    assert dense.occlusion and dense.ai.area_per_agent == 0.8 and dense.camera.eye[1] == 1.7


def test_save_round_trips_atomically_and_keeps_a_backup(tmp_path):
    path = tmp_path / "mine.toml"
    scene = load_scene(SCENE_DIR / "unarmed_small.toml")
    assert save_scene(scene, path) is None  # nothing to back up yet
    first = path.read_bytes()
    assert load_scene(path) == scene
    changed = scene.with_overrides(agents=99, roles={"run": "crawl"})
    backup = save_scene(changed, path)
    assert backup == tmp_path / "mine.toml.bak" and backup.read_bytes() == first
    again = load_scene(path)
    assert again.agents == 99 and again.roles == {"run": "crawl"} and again.camera == scene.camera
    source = changed.with_overrides(bake_fps="source", interpolation="dq_lerp")
    save_scene(source, path)
    assert load_scene(path) == source and source.pipeline_config().bake_fps == "source"


def test_a_failed_save_leaves_the_old_file_whole(tmp_path, monkeypatch):
    path = tmp_path / "mine.toml"
    save_scene(Scene(agents=5), path)
    before = path.read_bytes()
    real_replace = os.replace

    def failing_replace(src, dst):
        if str(dst) == str(path):
            raise OSError("disk full")
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError, match="disk full"):
        save_scene(Scene(agents=6), path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.toml", "mine.toml.bak"]  # no half-written temporaries


@pytest.mark.parametrize("text, words", [
    ("[scene\nagents = 3", "not valid TOML"),
    ("[scene]\nagents = 3\nspeed = 2", "unknown key 'speed' in [scene]"),
    ("[lights]\nsun = 1", "unknown table [lights]"),
    ("[scene]\nagents = -1", "scene.agents: agent count must be a whole number from 0 to 1000000, got -1"),
    ("[scene]\nagents = 2.5", "scene.agents: agent count must be a whole number"),
    ("[clips]\nprecision = 'f8'", "clips.precision"),
    ("[clips]\nbake_fps = 0", "clips.bake_fps: bake rate must be 1 to 240 fps or 'source'"),
    ("[clips]\nbake_fps = 'sauce'", "clips.bake_fps: bake rate must be 1 to 240"),
    ("[clips]\ncompression_bound_mm = nan", "clips.compression_bound_mm: compression bound must be a number from 0.001 to 100, got nan"),
    ("[clips]\ncompression_bound_mm = 0", "clips.compression_bound_mm: compression bound must be a number from 0.001 to 100, got 0"),
    ("[clips]\ncompression_bound_mm = '0.5'", "clips.compression_bound_mm: compression bound must be a number"),
    ("[clips]\ninterpolation = 'slerp'", "clips.interpolation: interpolation must be one of dq_lerp, qt_lerp, qt_corrected, qt_cubic"),
    ("[clips]\nroles = { jump = 'run' }", "unknown role 'jump'"),
    ("[features]\nlod_distances = [40.0, 14.0, 90.0]", "features.lod_distances: LOD distances must be three numbers above 0, each no larger than the next"),
    ("[features]\nlod_distances = [14.0, 40.0]", "features.lod_distances: LOD distances must be three numbers above 0, each no larger than the next, got [14.0, 40.0]"),
    ("[features]\nreadback_latency = 0", "features.readback_latency: readback latency must be a whole number from 1 to 3"),
    ("[features]\nshadows = 'yes'", "features.shadows: shadows must be true or false"),
    ("[ai]\nsubstep = -1.0", "ai.substep: AI setting substep must be a number above 0"),
    ("[ai]\nwings = 2", "unknown key 'wings' in [ai]"),
    ("[camera]\neye = [1.0, 2.0]", "needs both eye and target"),
    ("[camera]\neye = [1, 2, 3]\ntarget = [1, 2, 3]", "eye apart from target"),
])
def test_bad_scene_files_get_one_line_errors(tmp_path, text, words):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(SceneError) as info:
        load_scene(path)
    message = str(info.value)
    assert words in message and str(path) in message and "\n" not in message


def test_a_scene_bakes_only_the_clips_it_plays(tmp_path, gl_context):
    scene = Scene(agents=3, characters=(CharacterEntry(roles={"run": "crawl"}),), weapons=False, shadows=False)
    stats = run_headless(scene.pipeline_config(), 2, SIZE, ctx=gl_context)
    assert stats["bake"]["clips"] == ["idle", "shamble", "crawl", "attack", "hit", "death"]  # no "run"


def test_unarmed_scene_has_no_readback_at_all(gl_context):
    small = load_scene(SCENE_DIR / "unarmed_small.toml")
    stats = run_headless(small.pipeline_config(), 3, SIZE, ctx=gl_context, camera=small.camera_for(SIZE[0] / SIZE[1]))
    assert not {"readback", "gather", "transfer", "attach", "weapons"} & set(stats["passes_run"])
    assert "readback" not in stats["gpu_bytes"] and "weapons" not in stats["gpu_bytes"]
    assert stats["readback_wait_ms"] is None and stats["agents"] == 24


def test_overrides_name_the_flag_and_merge_roles():
    scene = Scene(characters=(CharacterEntry(roles={"walk": "shamble"}),))
    merged = scene.with_overrides(roles={"run": "crawl"}, agents=7, shadows=False)
    assert merged.roles == {"walk": "shamble", "run": "crawl"} and merged.agents == 7 and not merged.shadows
    with pytest.raises(SceneError, match="^--agents: agent count must be a whole number from 0 to"):
        scene.with_overrides(agents=-3)
    with pytest.raises(SceneError, match="^--bake-fps: bake rate must be 1 to 240"):
        scene.with_overrides(bake_fps=1000.0)
    with pytest.raises(SceneError, match="unknown scene setting"):
        scene.with_overrides(wings=2)


def test_cli_keeps_the_defaults_when_the_scene_file_is_broken(tmp_path):
    bad = tmp_path / "broken.toml"
    bad.write_text("[scene]\nagents = 'many'\n")
    out = subprocess.run([sys.executable, "-m", "app.demo", "--headless", "--scene", str(bad), "--frames", "1", "--size", "64x36",
                          "--agents", "2", "--screenshot", str(tmp_path / "x.png")], cwd=ROOT, capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr
    assert "scene.agents: agent count must be a whole number" in out.stderr and "running the default scene instead" in out.stderr
    assert "Traceback" not in out.stderr and (tmp_path / "x.png").exists()


def test_a_compressed_scene_runs_and_keeps_its_bound_through_a_save(tmp_path, gl_context):
    path = tmp_path / "packed.toml"
    path.write_text("[scene]\nagents = 3\n[clips]\nprecision = 'compressed'\ncompression_bound_mm = 0.2\n")
    scene = load_scene(path)
    assert (scene.precision, scene.compression_bound_mm) == ("compressed", 0.2)
    stats = run_headless(dataclasses.replace(scene.pipeline_config(), weapons=False, shadows=False), 2, SIZE, ctx=gl_context)
    assert stats["bake"]["precision"] == "compressed" and stats["bake"]["compression"]["bound_mm"] == 0.2
    assert stats["bake"]["compression"]["max_key_error_mm"] <= 0.2 and stats["nan_count"] == 0
    save_scene(scene, tmp_path / "again.toml")
    assert load_scene(tmp_path / "again.toml").compression_bound_mm == 0.2
