"""Several skins in one glTF file (issue 18, point 1): skins whose joints hang in the main skin's joint
trees are merged into one skeleton (a joint listed with another inverse bind gets a duplicate child at
identity rest), skins on another joint tree are other characters and are left out with one line.
The meshes are checked as the file has them (merge=False): merged, the skins' meshes share one draw."""

from __future__ import annotations

import json

import numpy as np
import pytest

from crowd.anim import reference
from crowd.anim.processor_programs import MAX_JOINTS as PROCESSOR_MAX_JOINTS
from crowd.asset import gltf
from crowd.asset.gltf import skins
from crowd.asset.gltf import load_character
from crowd.asset.gltf.reader import GltfImportError
from gltf_factory import (EXTRA_POSITIONS, KEY_TIMES, add_skin, bind_worlds, expected_extra_skinning, expected_skinning,
                          joint_worlds, make_gltf)


def skinned_at_key(character, key: int, mesh_name: str) -> np.ndarray:
    clip = character.clips[0]
    phase = (KEY_TIMES[key] - clip.start) / clip.duration
    pose = reference.sample_clip(character.skeleton, clip, np.array([phase]))
    m = reference.skinning_matrices(character.skeleton, pose)
    mesh = next(m for m in character.meshes if m.name == mesh_name)
    return reference.skin_points(m, mesh.positions, mesh.joints, mesh.weights)[0]


def skin_warnings(character) -> list[str]:
    return [w for w in character.warnings if "skin" in w]


def test_a_visor_skin_over_the_head_joints_is_merged_without_duplicates(tmp_path):
    path = make_gltf(tmp_path)
    visor = add_skin(path, "visor")
    c = load_character(path, merge=False)
    assert c.skeleton.names == ("root", "mid", "tip")
    assert skin_warnings(c) == ["merged skins 0, 1 into one skeleton (3 joints; 0 duplicated for differing inverse binds)"]
    assert [m.name for m in c.meshes] == ["body", "visor1"]
    for key in range(3):
        np.testing.assert_allclose(skinned_at_key(c, key, "body"), expected_skinning(key), atol=1e-5)
        np.testing.assert_allclose(skinned_at_key(c, key, "visor1"), expected_extra_skinning(visor, key), atol=1e-5)


@pytest.mark.parametrize("scale, rotation", [(1.0, False), (0.01, True), (100.0, False)])
def test_a_skin_with_other_inverse_binds_draws_through_duplicate_joints(tmp_path, scale, rotation):
    path = make_gltf(tmp_path, armature_scale=scale, armature_rotation=rotation)
    offset = add_skin(path, "offset", armature_scale=scale, armature_rotation=rotation)
    c = load_character(path, merge=False)
    sk = c.skeleton
    assert skin_warnings(c) == ["merged skins 0, 1 into one skeleton (6 joints; 3 duplicated for differing inverse binds)"]
    assert sk.names == ("root", "mid", "tip", "mid@skin1", "tip@skin1", "root@skin1")  # in the skin's order
    assert sk.parents.tolist() == [-1, 0, 1, 1, 2, 0]
    np.testing.assert_allclose(sk.rest_translation[3:], 0.0)
    np.testing.assert_allclose(sk.rest_rotation[3:], [[0, 0, 0, 1]] * 3)
    np.testing.assert_allclose(sk.rest_scale, 1.0, atol=1e-6)  # the factor is taken out of the duplicates too
    assert all(ch.joint < 3 for clip in c.clips for ch in clip.channels)  # duplicates have no channels
    body, extra = (next(m for m in c.meshes if m.name == n) for n in ("body", "offset1"))
    assert body.joints.max() < 3 and set(np.unique(extra.joints[extra.weights > 0])) <= {3, 4, 5}
    for key in range(3):
        np.testing.assert_allclose(skinned_at_key(c, key, "body"), expected_skinning(key, scale, rotation), atol=1e-5 * max(scale, 1))
        got = skinned_at_key(c, key, "offset1")
        want = expected_extra_skinning(offset, key, scale, rotation)
        np.testing.assert_allclose(got, want, atol=1e-5 * max(scale, 1))
        # The known shape: the offset mesh skins as EXTRA_POSITIONS in the main bind space would.
        main = joint_worlds(key, scale, rotation) @ np.linalg.inv(bind_worlds(scale, rotation))
        p = np.c_[EXTRA_POSITIONS, np.ones(4)]
        w = offset["weights"]
        shape = sum(w[:, k, None] * np.einsum("vij,vj->vi", main[offset["joints"]][offset["vertex_joints"][:, k]], p)[:, :3]
                    for k in range(4))
        np.testing.assert_allclose(got, shape, atol=1e-5 * max(scale, 1))


def test_a_separate_character_is_left_out_in_one_line(tmp_path):
    path = make_gltf(tmp_path)
    add_skin(path, "separate", name="Bob")
    c = load_character(path, merge=False)
    assert skin_warnings(c) == ["skin 1 ('Bob', 3 joints) shares no joint tree with skin 0: it is another character; left out"]
    assert c.skeleton.joint_count == 3 and [m.name for m in c.meshes] == ["body"]
    np.testing.assert_allclose(skinned_at_key(c, 1, "body"), expected_skinning(1), atol=1e-5)


def test_three_skins_merge_two_and_leave_out_one(tmp_path):
    path = make_gltf(tmp_path)
    visor = add_skin(path, "visor")
    add_skin(path, "separate")
    c = load_character(path, merge=False)
    assert skin_warnings(c) == [
        "skin 2 (3 joints) shares no joint tree with skin 0: it is another character; left out",
        "merged skins 0, 1 into one skeleton (3 joints; 0 duplicated for differing inverse binds)"]
    assert c.skeleton.joint_count == 3 and [m.name for m in c.meshes] == ["body", "visor1"]
    np.testing.assert_allclose(skinned_at_key(c, 2, "visor1"), expected_extra_skinning(visor, 2), atol=1e-5)


def test_a_skin_straddling_two_joint_trees_is_left_out(tmp_path):
    path = make_gltf(tmp_path)
    add_skin(path, "separate")
    doc = json.loads(path.read_text())
    doc["skins"][1]["joints"][2] = 3  # tip2 → the main character's tip
    path.write_text(json.dumps(doc))
    c = load_character(path, merge=False)
    assert skin_warnings(c) == ["skin 1 (3 joints) has 2 joints outside skin 0's joint trees: it does not fit one skeleton with it; left out"]
    assert c.skeleton.joint_count == 3


def test_a_skin_over_joints_the_main_skin_does_not_list_brings_them_in(tmp_path):
    # The visor's first joint becomes "antenna", hung under tip through a non-joint node, both at
    # identity: its bind is tip's, so the visor skins as before, and the skeleton gains the joint.
    path = make_gltf(tmp_path)
    visor = add_skin(path, "visor")
    doc = json.loads(path.read_text())
    holder, antenna = len(doc["nodes"]), len(doc["nodes"]) + 1
    doc["nodes"][3]["children"] = [holder]
    doc["nodes"] += [{"name": "holder", "children": [antenna]}, {"name": "antenna"}]
    doc["skins"][1]["joints"] = [antenna, 2]
    path.write_text(json.dumps(doc))
    c = load_character(path, merge=False)
    assert c.skeleton.names == ("root", "mid", "tip", "antenna") and c.skeleton.parents.tolist() == [-1, 0, 1, 2]
    assert skin_warnings(c) == ["merged skins 0, 1 into one skeleton (4 joints; 0 duplicated for differing inverse binds)"]
    for key in range(3):
        np.testing.assert_allclose(skinned_at_key(c, key, "body"), expected_skinning(key), atol=1e-5)
        np.testing.assert_allclose(skinned_at_key(c, key, "visor1"), expected_extra_skinning(visor, key), atol=1e-5)


def test_a_mesh_drawn_with_two_merged_skins_is_read_once_per_skin(tmp_path):
    path = make_gltf(tmp_path)
    add_skin(path, "visor")
    doc = json.loads(path.read_text())
    doc["nodes"].append({"name": "visor on the main skin", "mesh": 1, "skin": 0})
    doc["scenes"][0]["nodes"].append(len(doc["nodes"]) - 1)
    path.write_text(json.dumps(doc))
    c = load_character(path, merge=False)
    assert [m.name for m in c.meshes] == ["body", "visor1", "visor1@skin0"]
    a, b = c.meshes[1], c.meshes[2]
    # The same JOINTS_0 index different joint lists: skin 1's [tip, mid], skin 0's [root, mid, tip].
    assert a.joints[1, 0] == 2 and b.joints[1, 0] == 0


@pytest.mark.parametrize("mutate, needle", [
    (lambda d: d["skins"][1].update(joints=[3, 99]), "joint node index 99 is out of range"),
    (lambda d: d["skins"][1].update(joints=[3, "2"]), "joint node index '2' is out of range"),
    (lambda d: d["skins"][1].update(joints=[3, 3]), "skin 1 lists a joint twice"),
    (lambda d: d["skins"][1].update(joints=[]), "skin 1 has no joints"),
    (lambda d: d["skins"][1].update(inverseBindMatrices=99), "skin 1: inverseBindMatrices 99 is out of range"),
    (lambda d: d["skins"][1].update(joints=[3]), "visor1 references joint 1 but the skin has 1"),
    (lambda d: d["nodes"][-1].update(skin=7), "skin 7 is out of range"),
])
def test_a_bad_second_skin_is_refused_in_one_line(tmp_path, mutate, needle):
    path = make_gltf(tmp_path)
    add_skin(path, "visor")
    doc = json.loads(path.read_text())
    mutate(doc)
    path.write_text(json.dumps(doc))
    with pytest.raises(GltfImportError) as err:
        load_character(path)
    message = str(err.value)
    assert needle in message and message.startswith("test.gltf: ") and len(message.splitlines()) == 1
    assert gltf._UNEXPECTED not in message


def test_the_joint_budget_counts_the_union_and_the_duplicates(tmp_path, monkeypatch):
    path = make_gltf(tmp_path)
    add_skin(path, "offset")
    monkeypatch.setattr(skins, "MAX_JOINTS", 5)
    with pytest.raises(GltfImportError, match="skins 0, 1 need more than the 5 joints a vertex can address"):
        load_character(path)


def test_more_joints_than_the_processor_draws_are_refused_in_one_line(tmp_path, gl_context):
    # The importer allows up to 65,536 joints (a vertex's uint16); the processor draws 256 and says so.
    from crowd.pipeline import CrowdPipeline
    from crowd.pipeline_config import PipelineConfig
    from crowd.anim.processor_inputs import ProcessorError

    path = make_gltf(tmp_path)
    doc = json.loads(path.read_text())
    first = len(doc["nodes"])
    doc["nodes"][3]["children"] = [first]
    doc["nodes"].extend({"name": f"tail{i}", "translation": [0, 0.001, 0], "children": [first + i + 1]} for i in range(PROCESSOR_MAX_JOINTS))
    del doc["nodes"][-1]["children"]
    doc["skins"][0]["joints"] += list(range(first, first + PROCESSOR_MAX_JOINTS))
    doc["skins"][0].pop("inverseBindMatrices")
    path.write_text(json.dumps(doc))
    assert load_character(path).skeleton.joint_count == PROCESSOR_MAX_JOINTS + 3
    with pytest.raises(ProcessorError) as err:
        CrowdPipeline(gl_context, PipelineConfig(agents=1, model=path, weapons=False))
    assert f"the processor handles 1 to {PROCESSOR_MAX_JOINTS} joints, this skeleton has {PROCESSOR_MAX_JOINTS + 3}" in str(err.value)
    assert len(str(err.value).splitlines()) == 1


def test_a_merged_character_draws(tmp_path, gl_context):
    from crowd.pipeline_config import PipelineConfig
    from crowd.sim.config import AIConfig
    from crowd.smoke import run_headless

    path = make_gltf(tmp_path)
    add_skin(path, "offset")
    add_skin(path, "separate")
    size = (160, 90)
    crowd = dict(agents=6, seed=3, shadows=False, weapons=False, ai=AIConfig(half_extent=2.0))
    background = run_headless(PipelineConfig(**{**crowd, "agents": 0}), 2, size, ctx=gl_context)["_image"].astype(int)
    stats = run_headless(PipelineConfig(**crowd, model=path), 2, size, ctx=gl_context)
    assert stats["nan_count"] == 0
    assert float((np.abs(stats["_image"].astype(int) - background).max(axis=2) > 30).mean()) > 0.001
