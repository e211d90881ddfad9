import json

import numpy as np
import pytest

from conftest import shared, shared_files
from crowd.anim import reference
from crowd.asset.gltf import load_character
from crowd.asset.gltf.reader import GltfImportError
from gltf_factory import KEY_TIMES, expected_skinning, make_gltf


def skinned_at_key(character, key: int) -> np.ndarray:
    clip = character.clips[0]
    phase = (KEY_TIMES[key] - clip.start) / clip.duration
    pose = reference.sample_clip(character.skeleton, clip, np.array([phase]))
    m = reference.skinning_matrices(character.skeleton, pose)
    mesh = character.meshes[0]
    return reference.skin_points(m, mesh.positions, mesh.joints, mesh.weights)[0]


@pytest.mark.parametrize("scale", [1.0, 0.01, 100.0])
@pytest.mark.parametrize("rotation", [False, True])
@pytest.mark.parametrize("use_matrix", [False, True])
def test_armature_transform_is_folded_and_scale_factored(tmp_path, scale, rotation, use_matrix):
    path = make_gltf(tmp_path, armature_scale=scale, armature_rotation=rotation, use_matrix=use_matrix)
    c = load_character(path)
    # Joint transforms come out rigid: the constant scale is factored into translations.
    assert np.allclose(c.skeleton.rest_scale, 1.0, atol=1e-6)
    for key in range(3):
        np.testing.assert_allclose(skinned_at_key(c, key), expected_skinning(key, scale, rotation), atol=1e-5 * max(scale, 1))


@pytest.mark.parametrize("joint_type", [5121, 5123])
@pytest.mark.parametrize("weight_type", [5126, 5121, 5123])
def test_joint_and_weight_component_types(tmp_path, joint_type, weight_type):
    c = load_character(make_gltf(tmp_path, joint_type=joint_type, weight_type=weight_type))
    w = c.meshes[0].weights
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-6)  # renormalised (the float file sums to 1.25)
    tol = 1e-5 if weight_type == 5126 else 2.0 / 255.0
    np.testing.assert_allclose(skinned_at_key(c, 1), expected_skinning(1), atol=tol * 3)


def test_interleaved_accessors_and_external_buffer(tmp_path):
    c = load_character(make_gltf(tmp_path, interleaved=True, buffer_mode="external", external_uri="bin/data.bin"))
    np.testing.assert_allclose(c.meshes[0].normals, np.tile([[0, 0, 1]], (6, 1)))
    np.testing.assert_allclose(skinned_at_key(c, 2), expected_skinning(2), atol=1e-5)


def test_external_buffer_outside_folder_is_refused(tmp_path):
    path = make_gltf(tmp_path / "model", buffer_mode="external", external_uri="../escape.bin")
    with pytest.raises(GltfImportError, match="outside the file's folder"):
        load_character(path)


@pytest.mark.parametrize("interpolation", ["LINEAR", "STEP", "CUBICSPLINE"])
def test_interpolations_at_keys_and_between(tmp_path, interpolation):
    c = load_character(make_gltf(tmp_path, interpolation=interpolation))
    clip = c.clips[0]
    assert clip.start == pytest.approx(0.5) and clip.duration == pytest.approx(1.0)  # starts after t = 0
    for key in range(3):
        np.testing.assert_allclose(skinned_at_key(c, key), expected_skinning(key), atol=1e-5)
    # Between keys 0 and 1 (t = 0.75): STEP holds key 0, LINEAR is half way, the flat-tangent spline too.
    mid = reference.sample_clip(c.skeleton, clip, np.array([0.25]))
    angle = 2 * np.arctan2(mid.rotation[0, 1, 2], mid.rotation[0, 1, 3])
    assert angle == pytest.approx({"STEP": 0.0, "LINEAR": 0.6, "CUBICSPLINE": 0.6}[interpolation], abs=1e-6)


def test_old_layout_one_animation_per_joint_is_merged(tmp_path):
    c = load_character(make_gltf(tmp_path, split_animations=True))
    assert len(c.clips) == 1
    assert {(ch.joint, ch.path) for ch in c.clips[0].channels} == {(0, "translation"), (1, "rotation")}
    assert any("merged 2 single-joint animations" in w for w in c.warnings)
    np.testing.assert_allclose(skinned_at_key(c, 2), expected_skinning(2), atol=1e-5)


def test_sparse_accessor_is_read(tmp_path):
    c = load_character(make_gltf(tmp_path, sparse=True))
    np.testing.assert_allclose(skinned_at_key(c, 1), expected_skinning(1), atol=1e-5)


def _corrupt(tmp_path, mutate):
    path = make_gltf(tmp_path)
    doc = json.loads(path.read_text())
    mutate(doc)
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d["accessors"][0].update(count=10_000), "reads .* bytes"),
        (lambda d: d["skins"].clear(), "no skin"),
        (lambda d: d["nodes"][3].update(children=[1]), "two parents|cycle"),
        (lambda d: d["accessors"][0].update(componentType=1234), "unknown componentType"),
        (lambda d: d["buffers"][0].update(uri="data:application/octet-stream;base64,AAAA"), "holds 3 bytes"),
        (lambda d: d["asset"].update(version="1.0"), "version"),
        (lambda d: d["skins"][0].update(joints=[1, 2, 99]), "out of range"),
        (lambda d: d["animations"][0]["samplers"][0].update(interpolation="BEZIER"), "interpolation"),
        (lambda d: d["meshes"][0]["primitives"][0]["attributes"].pop("WEIGHTS_0"), "no JOINTS_0/WEIGHTS_0"),
    ],
)
def test_malformed_files_get_one_line_errors(tmp_path, mutate, message):
    with pytest.raises(GltfImportError, match=message) as info:
        load_character(_corrupt(tmp_path, mutate))
    assert "\n" not in str(info.value)


def test_nan_keys_are_refused(tmp_path):
    path = make_gltf(tmp_path, buffer_mode="external")
    doc = json.loads(path.read_text())
    blob = bytearray((tmp_path / "test.bin").read_bytes())
    acc = doc["accessors"][doc["animations"][0]["samplers"][0]["output"]]
    view = doc["bufferViews"][acc["bufferView"]]
    blob[view["byteOffset"]: view["byteOffset"] + 4] = np.float32(np.nan).tobytes()
    (tmp_path / "test.bin").write_bytes(bytes(blob))
    with pytest.raises(GltfImportError, match="NaN"):
        load_character(path)


def test_not_a_gltf_file(tmp_path):
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"glTF\x02\x00\x00\x00garbage")
    with pytest.raises(GltfImportError, match="bad.glb"):
        load_character(bad)
    with pytest.raises(GltfImportError, match="no such file"):
        load_character(tmp_path / "missing.gltf")


def test_clip_selection_names_unknown_clips(zombie):
    c = load_character(None, clips=["shamble", "idle"])
    assert [x.name for x in c.clips] == ["shamble", "idle"]
    with pytest.raises(GltfImportError, match="no clip named 'moonwalk'"):
        load_character(None, clips=["moonwalk"])


@pytest.mark.parametrize("path", shared_files(), ids=lambda p: p.name)
def test_shared_files_import_and_bind_pose_is_consistent(path):
    c = load_character(path)
    assert c.skeleton.joint_count >= 2 and c.meshes and c.clips
    for m in c.meshes:
        assert np.allclose(m.weights.sum(1), 1.0, atol=1e-5)
    # Skinning with the skin's own bind pose (global = inverse(IBM)) returns the mesh unchanged.
    bind = np.linalg.inv(c.skeleton.inverse_bind)
    m = (bind @ c.skeleton.inverse_bind)[None]
    mesh = c.meshes[0]
    np.testing.assert_allclose(reference.skin_points(m, mesh.positions, mesh.joints, mesh.weights)[0], mesh.positions, atol=1e-4)


def test_cesium_man_matrix_root_and_late_start():
    c = load_character(shared("CesiumMan.glb"))
    assert c.skeleton.joint_count == 19
    assert c.clips[0].start == pytest.approx(0.0417, abs=1e-3)
    # The skinned mesh stays upright and human-sized through the clip (a wrong root matrix would lay it down).
    pose = reference.sample_clip(c.skeleton, c.clips[0], np.linspace(0, 1, 5))
    pts = reference.skin_points(reference.skinning_matrices(c.skeleton, pose), c.meshes[0].positions[::50],
                                c.meshes[0].joints[::50], c.meshes[0].weights[::50])
    extent = pts.max(1) - pts.min(1)
    assert np.all(extent.max(1) > 1.0) and np.all(extent.max(1) < 2.5)


def test_two_skinned_meshes_share_one_skin():
    c = load_character(shared("Quaternius_Zombie_Basic.gltf"), merge=False)  # (merged, one draw)
    assert len(c.meshes) == 2 and c.skeleton.joint_count == 50
    assert {"Walk", "Run", "Idle", "Death"} <= {k.name for k in c.clips}
    assert c.clip("Walk").loop and not c.clip("Death").loop


def test_rigid_weapons_parented_to_joints_become_skinned_pieces():
    """Issue 18, point 1: the rigid meshes on Matt's hand are drawn with the body, as pieces weighted 1
    to their joint; skinned at any pose they sit where joint_world @ offset puts them."""
    from crowd.anim import reference
    from crowd.asset import gltf as gltf_module
    from crowd.asset.gltf.reader import Reader

    c = load_character(shared("Quaternius_Characters_Matt_SingleWeapon.gltf"), merge=False)  # (merged, they share the body's draw)
    assert not c.attachments
    rigid = [m for m in c.meshes if m.piece.startswith("rigid")]
    assert len(rigid) == 2
    sk = c.skeleton
    for m in rigid:
        assert m.triangle_count > 0 and np.all(m.weights[:, 0] == 1.0) and len(set(m.joints[:, 0].tolist())) == 1
        chain, j = [], int(m.joints[0, 0])
        while j >= 0:
            chain.append(sk.names[j])
            j = sk.parents[j]
        assert "LowerArm.L" in chain  # both weapons ride on the left hand's finger joint
    # The same file's attachments, as the importer found them, against the pieces made of them.
    raw = gltf_module._import(Reader(shared("Quaternius_Characters_Matt_SingleWeapon.gltf")))
    assert len(raw.attachments) == 2
    pose = reference.sample_clip(sk, c.clips[3], np.array([0.4]))
    world = reference.global_matrices(sk, pose)[0]
    skin = reference.skinning_matrices(sk, pose)
    for a, m in zip(raw.attachments, rigid):
        expected = (np.c_[a.mesh.positions, np.ones(len(a.mesh.positions))] @ (world[a.joint] @ a.offset).T)[:, :3]
        drawn = reference.skin_points(skin, m.positions, m.joints, m.weights)[0]
        np.testing.assert_allclose(drawn, expected, atol=1e-5)


def test_hedgehog_animated_scale_is_kept():
    c = load_character(shared("Quaternius_CubeWorld_Hedgehog.gltf"))
    scale_channels = [ch for clip in c.clips for ch in clip.channels if ch.path == "scale"]
    assert scale_channels
    assert max(float(np.max(ch.values)) for ch in scale_channels) > 1.1


def test_spec_leniencies_still_load(tmp_path):
    """What glTF allows, or what old exporters write, that a strict reader could wrongly refuse."""
    def variant(name, mutate):
        path = make_gltf(tmp_path / name)
        doc = json.loads(path.read_text())
        mutate(doc)
        path.write_text(json.dumps(doc))
        return load_character(path)

    reference = load_character(make_gltf(tmp_path / "plain"))

    # glTF: the inverse bind accessor holds at least one matrix per joint; the extra ones are unused.
    path = make_gltf(tmp_path / "ibm", buffer_mode="external")
    doc = json.loads(path.read_text())
    ibm = doc["accessors"][doc["skins"][0]["inverseBindMatrices"]]
    view = doc["bufferViews"][ibm["bufferView"]]
    blob = (tmp_path / "ibm" / "test.bin").read_bytes()
    matrices = blob[view["byteOffset"]: view["byteOffset"] + view["byteLength"]] + np.eye(4, dtype=np.float32).tobytes()
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(matrices)})
    doc["buffers"][0]["byteLength"] = len(blob) + len(matrices)
    doc["accessors"].append(dict(ibm, bufferView=len(doc["bufferViews"]) - 1, count=4))
    doc["skins"][0]["inverseBindMatrices"] = len(doc["accessors"]) - 1
    (tmp_path / "ibm" / "test.bin").write_bytes(blob + matrices)
    path.write_text(json.dumps(doc))
    np.testing.assert_array_equal(load_character(path).skeleton.inverse_bind, reference.skeleton.inverse_bind)
    # byteStride 0 (glTF 1.0's "tightly packed"), required extensions that change nothing here, an
    # explicit identity matrix.
    for name, mutate in [("stride0", lambda d: d["bufferViews"][0].update(byteStride=0)),
                         ("ext", lambda d: d.update(extensionsRequired=["KHR_materials_unlit", "KHR_texture_transform"])),
                         ("matrix", lambda d: d["nodes"][3].update(matrix=[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 1, 0, 1]))]:
        c = variant(name, mutate)
        np.testing.assert_array_equal(c.meshes[0].positions, reference.meshes[0].positions)
        np.testing.assert_allclose(c.skeleton.rest_translation, reference.skeleton.rest_translation)


def test_glb_json_chunk_padding_and_byte_order_mark(tmp_path):
    import struct

    from crowd.asset.zombie import ASSET_PATH

    data = ASSET_PATH.read_bytes()
    n = struct.unpack_from("<I", data, 12)[0]
    js, rest = data[20:20 + n].rstrip(b" "), data[20 + n:]
    js = b"\xef\xbb\xbf" + js  # a BOM, and zeros instead of spaces: written by some tools, harmless
    js += b"\x00" * (-len(js) % 4)
    glb = struct.pack("<I4s", len(js), b"JSON") + js + rest
    path = tmp_path / "zombie.glb"
    path.write_bytes(b"glTF" + struct.pack("<II", 2, 12 + len(glb)) + glb)
    assert [c.name for c in load_character(path).clips] == [c.name for c in load_character(ASSET_PATH).clips]
