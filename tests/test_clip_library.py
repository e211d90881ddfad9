"""Clips from other files (issue 44, point 3): a body without clips takes a library's (a pack's animation
library, Mixamo's animations without the character), matched to its joints by name; what matched and what
was left out is said in one line; a scene names the files per character, the command line with --clips."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from crowd.anim import reference
from crowd.asset.gltf import load_character
from crowd.asset.gltf.reader import GltfImportError
from crowd.scene import CharacterEntry, Scene, load_scene, save_scene
from gltf_factory import KEY_TIMES, clipless_gltf, expected_skinning, library_gltf, make_gltf

ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]


def _skinned(c, key):
    clip = c.clips[0]
    pose = reference.sample_clip(c.skeleton, clip, np.array([(KEY_TIMES[key] - clip.start) / clip.duration]))
    mesh = c.meshes[0]
    return reference.skin_points(reference.skinning_matrices(c.skeleton, pose), mesh.positions, mesh.joints, mesh.weights)[0]


def test_a_body_without_clips_is_refused_alone_and_plays_a_librarys(tmp_path):
    body = clipless_gltf(tmp_path)
    with pytest.raises(GltfImportError, match="no clips, and the built-in clips cannot be retargeted to it"):
        load_character(body)
    c = load_character(body, scale=1.0, libraries=[library_gltf(tmp_path)])
    assert [clip.name for clip in c.clips] == ["wave"]
    assert c.warnings == ["clips from library.gltf: 1 (wave); 3 of the character's 3 joints matched by name, 2 animated; "
                          "2 named nodes of the file matched no joint"]
    for key in range(3):  # the same rig: the pose is the one the file with its own clip has
        np.testing.assert_allclose(_skinned(c, key), expected_skinning(key), atol=1e-5)


def test_a_bone_of_another_length_keeps_the_characters(tmp_path):
    c = load_character(clipless_gltf(tmp_path), scale=1.0, libraries=[library_gltf(tmp_path, mid_length=1.6)])
    assert any("translation keys of 1 joints left out, their bones being another length (mid)" in w for w in c.warnings)
    for key in range(3):
        np.testing.assert_allclose(_skinned(c, key), expected_skinning(key), atol=1e-5)


def test_a_clip_name_taken_gets_the_files_name_and_a_file_matching_nothing_is_refused(tmp_path):
    c = load_character(make_gltf(tmp_path, "own.gltf"), scale=1.0, libraries=[library_gltf(tmp_path)])
    assert [clip.name for clip in c.clips] == ["wave", "wave.library"]
    other = library_gltf(tmp_path, "other.gltf")
    text = other.read_text().replace('"root"', '"Hips"').replace('"mid"', '"Spine"').replace('"tip"', '"Head"')
    other.write_text(text)
    with pytest.raises(GltfImportError, match=r"other.gltf: no node is named as a joint of the character") as info:
        load_character(clipless_gltf(tmp_path), libraries=[other])
    assert "\n" not in str(info.value)
    with pytest.raises(GltfImportError, match="missing.gltf: no such file"):
        load_character(clipless_gltf(tmp_path), libraries=[tmp_path / "missing.gltf"])


def test_a_scene_names_the_files_per_character_and_keeps_them(tmp_path):
    body, library = clipless_gltf(tmp_path), library_gltf(tmp_path)
    (tmp_path / "crowd.toml").write_text(f'[[characters]]\nmodel = "{body.name}"\nclips = ["{library.name}"]\n\n'
                                         '[[characters]]\nmodel = "brute"\n')
    scene = load_scene(tmp_path / "crowd.toml")
    assert scene.characters[0].clips == (library,) and scene.characters[0].spec().clips == (library,)
    save_scene(scene, tmp_path / "again.toml")
    assert load_scene(tmp_path / "again.toml").characters[0].clips == (library,)
    one = Scene(characters=(CharacterEntry(body, clips=(library,)),))
    save_scene(one, tmp_path / "one.toml")
    assert "files = [" in (tmp_path / "one.toml").read_text() and load_scene(tmp_path / "one.toml").characters[0].clips == (library,)


def test_the_demo_takes_clips_from_a_file(tmp_path):
    body, library = clipless_gltf(tmp_path), library_gltf(tmp_path)
    out = subprocess.run([sys.executable, "-m", "app.demo", "--headless", "--model", str(body), "--clips", str(library), "--frames", "2",
                          "--size", "64x36", "--agents", "3", "--screenshot", str(tmp_path / "shot.png")],
                         capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    bad = subprocess.run([sys.executable, "-m", "app.demo", "--headless", "--model", str(body), "--clips", str(tmp_path / "nope.glb")],
                         capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr and "--clips" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
