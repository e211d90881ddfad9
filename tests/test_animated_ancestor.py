"""An animated node above the skin's joints (issue 44, point 2): in a real walk the node above every joint
turned up to 34 degrees from rest and was folded in at rest. Such a node becomes a joint of the skeleton,
so the drawn pose is glTF's; a channel still left out is named once, saying whether it moves anything
drawn."""

from __future__ import annotations

import json

import numpy as np
import pytest

from crowd import transforms as tf
from crowd.anim import reference
from crowd.asset.gltf import load_character
from gltf_factory import KEY_TIMES, add_channel, armature_matrix, expected_skinning, make_gltf

TURNS = np.array([0.0, 0.35, 0.6])  # radians about Y of the armature node at KEY_TIMES (34 degrees at the last)


def _animated_armature(tmp_path, scale: float, extra=None):
    path = make_gltf(tmp_path, armature_scale=scale)
    doc = json.loads(path.read_text())
    t, q, s, _ = tf.mat4_decompose(armature_matrix(scale, False))
    add_channel(doc, 0, "rotation", tf.quat_mul(tf.quat_from_axis_angle([0.0, 1.0, 0.0], TURNS), q[None]))
    if extra:
        extra(doc)
    path.write_text(json.dumps(doc))
    return path, (t, q, s)


@pytest.mark.parametrize("scale", [1.0, 0.01])
def test_the_animated_node_above_the_joints_is_played(tmp_path, scale):
    path, (t, q, s) = _animated_armature(tmp_path, scale)
    c = load_character(path, scale=1.0)
    assert list(c.skeleton.names[:1]) == ["Armature"] and c.skeleton.joint_count == 4
    assert not any("left out" in w for w in c.warnings)
    clip = c.clips[0]
    rest = armature_matrix(scale, False)
    worst = 0.0
    for key in range(3):
        moved = tf.trs_to_mat4(t, tf.quat_mul(tf.quat_from_axis_angle([0.0, 1.0, 0.0], TURNS[key]), q), s)
        expect = expected_skinning(key, scale)
        expect = (np.c_[expect, np.ones(len(expect))] @ (moved @ np.linalg.inv(rest)).T)[:, :3]
        phase = (KEY_TIMES[key] - clip.start) / clip.duration
        pose = reference.sample_clip(c.skeleton, clip, np.array([phase]))
        mesh = c.meshes[0]
        got = reference.skin_points(reference.skinning_matrices(c.skeleton, pose), mesh.positions, mesh.joints, mesh.weights)[0]
        worst = max(worst, float(np.abs(got - expect).max()))
    assert worst <= 1e-4 * scale, worst  # 0.1 mm at a person's size (float32 keys)


def test_channels_still_left_out_are_named_once_with_what_they_move(tmp_path):
    def more(doc):
        # A camera at the scene's root, turned by the clip: it moves nothing drawn.
        doc["nodes"].append({"name": "Camera"})
        doc["scenes"][0]["nodes"].append(len(doc["nodes"]) - 1)
        add_channel(doc, len(doc["nodes"]) - 1, "rotation", tf.quat_from_axis_angle([0.0, 1.0, 0.0], TURNS))
        add_channel(doc, len(doc["nodes"]) - 1, "translation", np.zeros((3, 3)))

    c = load_character(_animated_armature(tmp_path, 1.0, more)[0], scale=1.0)
    notes = [w for w in c.warnings if "left out" in w]
    assert notes == ["node 5 ('Camera'): its rotation, translation channels (1 clip) are left out; it moves nothing drawn"], notes


def test_an_animated_mesh_on_a_joint_is_named_as_moving_what_is_drawn(tmp_path):
    def hat(doc):
        doc["nodes"].append({"name": "hat", "mesh": 0})  # a rigid mesh hanging on the tip joint
        doc["nodes"][3]["children"] = [len(doc["nodes"]) - 1]
        add_channel(doc, len(doc["nodes"]) - 1, "rotation", tf.quat_from_axis_angle([0.0, 1.0, 0.0], TURNS))

    c = load_character(_animated_armature(tmp_path, 1.0, hat)[0], scale=1.0)
    notes = [w for w in c.warnings if "channels" in w and "left out" in w]
    assert notes == ["node 5 ('hat'): its rotation channels (1 clip) are left out; it moves mesh node 5 ('hat'), which is drawn still"], notes
