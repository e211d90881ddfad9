"""Files animated by their nodes and morph weights alone, without a skin (issue 44, point 5: the classic
vertex-animated birds and horses, morph test files): their mesh nodes become the skeleton, each mesh
weighted wholly to its node, and they are drawn and animated in the crowd like any other character."""

from __future__ import annotations

import json

import numpy as np
import pytest

from crowd import transforms as tf
from crowd.anim import reference
from crowd.asset.gltf import load_character
from crowd.asset.gltf.reader import GltfImportError
from crowd.asset.pose import morph_vertices, sample_morph_weights
from crowd.gl import Offscreen
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import PipelineConfig
from crowd.sim.config import AIConfig
from gltf_factory import (KEY_TIMES, MORPH_KEYS, MORPH_ONLY_TRANSLATION, MORPH_ONLY_TURNS, MORPH_POSITIONS, POSITIONS, make_gltf,
                          morph_only_gltf)


def test_the_mesh_node_is_the_skeleton_and_each_key_is_glTFs_pose(tmp_path):
    c = load_character(morph_only_gltf(tmp_path), scale=1.0)
    assert list(c.skeleton.names) == ["body"] and list(c.skeleton.parents) == [-1]
    assert any("no skin" in w for w in c.warnings)
    (mesh,) = c.meshes
    assert np.all(mesh.joints == 0) and np.all(mesh.weights[:, 0] == 1.0)
    (clip,) = c.clips
    assert clip.morph_channels and {ch.path for ch in clip.channels} == {"rotation"}
    for key in range(3):
        # glTF's meaning, in float64: the node's transform at the key times the morphed bind positions.
        morphed = POSITIONS.astype(np.float64) + np.einsum("t,tvc->vc", MORPH_KEYS[key], MORPH_POSITIONS.astype(np.float64))
        turn = tf.trs_to_mat4(MORPH_ONLY_TRANSLATION, tf.quat_from_axis_angle([0.0, 1.0, 0.0], MORPH_ONLY_TURNS[key]), np.ones(3))
        expect = (np.c_[morphed, np.ones(len(morphed))] @ turn.T)[:, :3]
        phase = (KEY_TIMES[key] - clip.start) / clip.duration
        pose = reference.sample_clip(c.skeleton, clip, np.array([phase]))
        weights = sample_morph_weights(c.morph_defaults, clip, [phase])[0]
        positions, _ = morph_vertices(mesh, weights)
        got = reference.skin_points(reference.skinning_matrices(c.skeleton, pose), positions, mesh.joints, mesh.weights)[0]
        np.testing.assert_allclose(got, expect, atol=1e-6)


def test_a_file_with_no_skin_and_nothing_animated_is_refused_in_one_line(tmp_path):
    path = morph_only_gltf(tmp_path, turn=False)
    doc = json.loads(path.read_text())
    doc.pop("animations")
    path.write_text(json.dumps(doc))
    with pytest.raises(GltfImportError, match="no skin, and no animation moves its mesh nodes or morph weights") as info:
        load_character(path)
    assert "\n" not in str(info.value)
    doc["nodes"][4].pop("mesh")
    path.write_text(json.dumps(doc))
    with pytest.raises(GltfImportError, match="no node draws a mesh"):
        load_character(path)


def test_a_skinned_file_is_read_as_before(tmp_path):
    c = load_character(make_gltf(tmp_path, morph=True), scale=1.0)
    assert c.skeleton.joint_count == 3 and not any("no skin" in w for w in c.warnings)


def test_a_crowd_of_it_is_drawn_and_its_morphs_move(gl_context, tmp_path):
    path = morph_only_gltf(tmp_path)
    config = PipelineConfig(model=path, agents=6, town=False, survivor=False, weapons=False, ai_path="cpu", impostors="off",
                            ai=AIConfig(half_extent=3.0))
    size = (160, 120)
    pictures = []
    with Offscreen(gl_context, size) as target, CrowdPipeline(gl_context, config) as p:
        p.camera = p.overview_camera(size[0] / size[1])
        for _ in range(2):
            for _ in range(20):
                p.frame(target.framebuffer, 1 / 60)
            pictures.append(np.frombuffer(target.framebuffer.read(), np.uint8).copy())
        assert "morph_weights" in p.passes_run and p.renderer.last["triangles"] > 0
        assert np.count_nonzero(p.processor.read_morph_pairs()[..., 1]) > 0
    assert not np.array_equal(pictures[0], pictures[1])  # the crowd moves
