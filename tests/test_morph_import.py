"""Morph targets read from glTF (issue 23, point 1): targets, names, default weights, weights channels in
every interpolation, sparse and dense accessors, the project's writer, and hostile files."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from crowd.asset.gltf import load_character
from crowd.asset.gltf.reader import GltfImportError
from crowd.asset.gltf_write import glb_bytes
from crowd.asset.model import ModelError
from crowd.asset.pose import morph_vertices, phase_to_time, sample_morph_weights
from crowd.asset.units import scale_character
from gltf_factory import (KEY_TIMES, MORPH_KEYS, MORPH_NAMES, MORPH_NORMALS, MORPH_POSITIONS, NODE_MORPH_WEIGHTS, POSITIONS,
                          make_gltf)


def _load(tmp_path, **kw):
    # scale=1: the test strip is 2 m tall, and its deltas are compared as authored.
    return load_character(make_gltf(tmp_path, morph=True, **kw), scale=1.0)


def _json(path):
    return json.loads(path.read_text())


def _rewrite(path, mutate):
    doc = _json(path)
    mutate(doc)
    path.write_text(json.dumps(doc))
    return path


def _glb_json(data: bytes) -> dict:
    length = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + length])


def test_targets_names_and_default_weights_are_read(tmp_path):
    c = _load(tmp_path)
    assert c.morphs == tuple(MORPH_NAMES)
    assert np.array_equal(c.morph_defaults, NODE_MORPH_WEIGHTS)  # the node's weights override the mesh's
    (mesh,) = c.meshes
    assert mesh.morph_targets.tolist() == [0, 1]
    assert np.array_equal(mesh.morph_positions, MORPH_POSITIONS) and np.array_equal(mesh.morph_normals, MORPH_NORMALS)
    assert not any("morph" in w for w in c.warnings)


def test_unnamed_targets_are_named_after_their_mesh_and_the_mesh_weights_hold_without_node_weights(tmp_path):
    def drop(doc):
        del doc["meshes"][0]["extras"], doc["nodes"][4]["weights"]
    c = load_character(_rewrite(make_gltf(tmp_path, morph=True), drop), scale=1.0)
    assert c.morphs == ("body.target0", "body.target1")
    assert np.array_equal(c.morph_defaults, [0.25, 0.0])


@pytest.mark.parametrize("interpolation", ["LINEAR", "STEP", "CUBICSPLINE"])
def test_weights_channels_play_as_gltf_says(tmp_path, interpolation):
    c = _load(tmp_path, interpolation=interpolation)
    clip = c.clips[0]
    (channel,) = clip.morph_channels
    assert channel.interpolation == interpolation and channel.morphs.tolist() == [0, 1]
    # At the keys, the keys; between them, what glTF's formula gives, computed here by hand.
    span = clip.end - clip.start
    keyed = sample_morph_weights(c.morph_defaults, clip, (KEY_TIMES - clip.start) / span)
    assert np.allclose(keyed, MORPH_KEYS, atol=1e-7)
    u = 0.3
    phase = (KEY_TIMES[0] + u * (KEY_TIMES[1] - KEY_TIMES[0]) - clip.start) / span
    got = sample_morph_weights(c.morph_defaults, clip, [phase])[0]
    if interpolation == "LINEAR":
        want = MORPH_KEYS[0] + u * (MORPH_KEYS[1] - MORPH_KEYS[0])
    elif interpolation == "STEP":
        want = MORPH_KEYS[0]
    else:  # Hermite with the factory's zero tangents
        want = (2 * u**3 - 3 * u**2 + 1) * MORPH_KEYS[0] + (-2 * u**3 + 3 * u**2) * MORPH_KEYS[1]
    assert np.allclose(got, want, atol=1e-7)
    assert phase_to_time(clip, phase) == pytest.approx(KEY_TIMES[0] + u * (KEY_TIMES[1] - KEY_TIMES[0]))


def test_a_morphed_vertex_is_the_base_plus_the_weighted_deltas(tmp_path):
    (mesh,) = _load(tmp_path).meshes
    weights = np.array([0.5, -0.25])
    positions, normals = morph_vertices(mesh, weights)
    want = POSITIONS + 0.5 * MORPH_POSITIONS[0] - 0.25 * MORPH_POSITIONS[1]
    assert np.allclose(positions, want, atol=1e-7)
    raw = np.tile([0.0, 0.0, 1.0], (6, 1)) + 0.5 * MORPH_NORMALS[0]
    assert np.allclose(normals, raw / np.linalg.norm(raw, axis=1, keepdims=True), atol=1e-7)


def test_a_clip_of_morph_weights_alone_is_kept(tmp_path):
    """A face clip (weights only) beside a body clip (joints only): both are clips."""
    path = make_gltf(tmp_path, morph=True)
    doc = _json(path)
    channels, samplers = doc["animations"][0]["channels"], doc["animations"][0]["samplers"]
    doc["animations"] = [{"name": "snarl", "samplers": samplers, "channels": [ch for ch in channels if ch["target"]["path"] == "weights"]},
                         {"name": "sway", "samplers": samplers, "channels": [ch for ch in channels if ch["target"]["path"] != "weights"]}]
    path.write_text(json.dumps(doc))
    c = load_character(path, scale=1.0)
    face, body = c.clip("snarl"), c.clip("sway")
    assert face.channels == [] and len(face.morph_channels) == 1
    assert sorted(ch.path for ch in body.channels) == ["rotation", "translation"] and body.morph_channels == []


@pytest.mark.parametrize("interpolation", ["LINEAR", "CUBICSPLINE"])
def test_the_writer_round_trips_morphs_sparse_and_dense_alike(tmp_path, interpolation):
    """The project's writer, sparse and dense: both files import to the same targets, defaults and weight
    keys as the source, so every morphed vertex is identical; the sparse one holds sparse accessors only
    for the targets, and the dense one none."""
    source = _load(tmp_path, interpolation=interpolation)
    loaded = {}
    for sparse in (True, False):
        data = glb_bytes(source, sparse=sparse)
        doc = _glb_json(data)
        (prim,) = doc["meshes"][0]["primitives"]
        for k, target in enumerate(prim["targets"]):
            for key, deltas in (("POSITION", MORPH_POSITIONS[k]), ("NORMAL", MORPH_NORMALS[k])):
                accessor = doc["accessors"][target[key]]
                assert ("sparse" in accessor) == (sparse and bool(np.any(deltas))), (sparse, k, key)
                assert ("bufferView" in accessor) == (not sparse), (sparse, k, key)
        path = tmp_path / f"round_{sparse}.glb"
        path.write_bytes(data)
        loaded[sparse] = load_character(path, scale=1.0)
    for c in loaded.values():
        assert c.morphs == source.morphs and np.array_equal(c.morph_defaults, source.morph_defaults)
        (mesh,) = c.meshes
        assert np.array_equal(mesh.morph_positions, source.meshes[0].morph_positions)
        assert np.array_equal(mesh.morph_normals, source.meshes[0].morph_normals)
        (ch,) = c.clips[0].morph_channels
        (want,) = source.clips[0].morph_channels
        assert ch.interpolation == want.interpolation and np.array_equal(ch.values, want.values.astype(np.float32))
    phases = np.linspace(0.0, 1.0, 41)
    for phase in phases:
        w = [sample_morph_weights(c.morph_defaults, c.clips[0], [phase])[0] for c in loaded.values()]
        assert np.array_equal(w[0], w[1])
        v = [morph_vertices(c.meshes[0], wk) for c, wk in zip(loaded.values(), w)]
        assert np.array_equal(v[0][0], v[1][0]) and np.array_equal(v[0][1], v[1][1])


def test_the_writer_picks_sparse_where_it_is_smaller(tmp_path):
    source = _load(tmp_path)
    doc = _glb_json(glb_bytes(source))
    positions = [t["POSITION"] for m in doc["meshes"] for p in m["primitives"] for t in p.get("targets", [])]
    # Each target moves 2 of 6 vertices: 2 x 14 bytes sparse against 6 x 12 dense.
    assert all("sparse" in doc["accessors"][a] for a in positions)


def test_the_writer_refuses_channels_it_cannot_merge(tmp_path):
    source = _load(tmp_path)
    clip = source.clips[0]
    (ch,) = clip.morph_channels
    import dataclasses
    split = [dataclasses.replace(ch, morphs=ch.morphs[:1], values=ch.values[:, :1]),
             dataclasses.replace(ch, morphs=ch.morphs[1:], values=ch.values[:, 1:], times=ch.times + 0.01)]
    broken = dataclasses.replace(source, clips=[dataclasses.replace(clip, morph_channels=split)])
    with pytest.raises(ModelError, match="different key times"):
        glb_bytes(broken)


def test_scaling_a_character_scales_its_position_deltas_only(tmp_path):
    c = _load(tmp_path)
    big = scale_character(c, 2.0)
    assert np.allclose(big.meshes[0].morph_positions, 2.0 * c.meshes[0].morph_positions)
    assert np.array_equal(big.meshes[0].morph_normals, c.meshes[0].morph_normals)


def test_tangent_deltas_are_left_out_with_a_warning(tmp_path):
    def tangent(doc):
        doc["meshes"][0]["primitives"][0]["targets"][0]["TANGENT"] = doc["meshes"][0]["primitives"][0]["targets"][0]["NORMAL"]
    c = load_character(_rewrite(make_gltf(tmp_path, morph=True), tangent), scale=1.0)
    assert any("TANGENT deltas left out" in w for w in c.warnings)


def test_sparse_targets_over_zeros_are_read(tmp_path):
    """A target written the way exporters write sparse ones: no bufferView, the moved vertices only."""
    source = _load(tmp_path)
    data = glb_bytes(source, sparse=True)
    path = tmp_path / "sparse.glb"
    path.write_bytes(data)
    c = load_character(path, scale=1.0)
    assert np.array_equal(c.meshes[0].morph_positions, MORPH_POSITIONS)


def _hostile(tmp_path, mutate, match):
    path = _rewrite(make_gltf(tmp_path, morph=True), mutate)
    with pytest.raises(GltfImportError) as info:
        load_character(path)
    message = str(info.value)
    assert "\n" not in message and message.startswith("test.gltf") and match in message, message


def _set_target_data(doc, target, key, values):
    """Points target `target`'s `key` at a new float accessor holding `values` (appended to the buffer)."""
    import base64

    uri = doc["buffers"][0]["uri"]
    blob = bytearray(base64.b64decode(uri.split(",", 1)[1]))
    while len(blob) % 4:
        blob.append(0)
    data = np.asarray(values, np.float32).tobytes()
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
    blob += data
    doc["buffers"][0].update(byteLength=len(blob), uri="data:application/octet-stream;base64," + base64.b64encode(bytes(blob)).decode())
    doc["accessors"].append({"bufferView": len(doc["bufferViews"]) - 1, "componentType": 5126, "count": len(values), "type": "VEC3"})
    doc["meshes"][0]["primitives"][0]["targets"][target][key] = len(doc["accessors"]) - 1


def test_a_nan_delta_is_refused_in_one_line(tmp_path):
    bad = MORPH_POSITIONS[0].copy()
    bad[3, 1] = np.nan
    _hostile(tmp_path, lambda doc: _set_target_data(doc, 0, "POSITION", bad), "target 0 POSITION): vertex 3 is NaN")


def test_a_huge_delta_is_refused_in_one_line(tmp_path):
    bad = MORPH_NORMALS[1].copy()
    bad[5, 0] = 3e38
    _hostile(tmp_path, lambda doc: _set_target_data(doc, 1, "NORMAL", bad), "target 1 NORMAL): vertex 5 moves beyond")


def test_a_target_of_the_wrong_length_is_refused(tmp_path):
    _hostile(tmp_path, lambda doc: _set_target_data(doc, 0, "POSITION", MORPH_POSITIONS[0][:4]), "has 4 elements for 6 vertices")


def test_weights_of_the_wrong_count_are_refused(tmp_path):
    def short(doc):
        sampler = doc["animations"][0]["samplers"][2]
        doc["accessors"][sampler["output"]]["count"] = 5
    _hostile(tmp_path, short, "5 weights for 3 keys of 2 targets")


@pytest.mark.parametrize("value, match", [(float("nan"), "NaN or infinity"), (1e9, "beyond ±10")])
def test_bad_default_weights_are_refused(tmp_path, value, match):
    def bad(doc):
        doc["nodes"][4]["weights"] = [0.5, value]
    path = _rewrite(make_gltf(tmp_path, morph=True), bad)  # (json writes NaN, which the importer's parser reads)
    with pytest.raises(GltfImportError) as info:
        load_character(path)
    assert match in str(info.value) and "\n" not in str(info.value)


def test_default_weights_of_the_wrong_length_are_refused(tmp_path):
    _hostile(tmp_path, lambda doc: doc["meshes"][0].update(weights=[1.0]), "weights must be 2 numbers")


def test_a_keyed_weight_beyond_bounds_is_refused(tmp_path):
    def big(doc):
        import base64

        sampler = doc["animations"][0]["samplers"][2]
        acc = doc["accessors"][sampler["output"]]
        view = doc["bufferViews"][acc["bufferView"]]
        blob = bytearray(base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1]))
        struct.pack_into("<f", blob, view["byteOffset"] + 4 * 3, 50.0)
        doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(bytes(blob)).decode()
    _hostile(tmp_path, big, "weight 3 is 50, beyond ±10")


def test_primitives_with_different_target_counts_are_refused(tmp_path):
    def second(doc):
        prim = dict(doc["meshes"][0]["primitives"][0])
        prim["targets"] = prim["targets"][:1]
        doc["meshes"][0]["primitives"].append(prim)
    _hostile(tmp_path, second, "different numbers of morph targets")


def test_a_weights_channel_on_a_node_without_targets_is_left_out(tmp_path):
    def retarget(doc):
        doc["animations"][0]["channels"][2]["target"]["node"] = 1
    c = load_character(_rewrite(make_gltf(tmp_path, morph=True), retarget), scale=1.0)
    assert c.clips[0].morph_channels == []
    assert any("draws no skinned mesh with morph targets; left out" in w for w in c.warnings)


def test_bad_target_names_fall_back_to_numbers_with_a_warning(tmp_path):
    c = load_character(_rewrite(make_gltf(tmp_path, morph=True), lambda doc: doc["meshes"][0]["extras"].update(targetNames=["a"])), scale=1.0)
    assert c.morphs == ("body.target0", "body.target1")
    assert any("targetNames is not 2 names" in w for w in c.warnings)


def test_repeated_target_names_are_told_apart(tmp_path):
    c = load_character(_rewrite(make_gltf(tmp_path, morph=True), lambda doc: doc["meshes"][0]["extras"].update(targetNames=["a", "a"])), scale=1.0)
    assert c.morphs == ("a", "a.1")


@pytest.mark.parametrize("sparse", [True, False])
def test_the_khronos_validator_passes_the_writers_morphs(tmp_path, sparse):
    from conftest import khronos_issues

    path = tmp_path / "morph.glb"
    path.write_bytes(glb_bytes(_load(tmp_path, interpolation="CUBICSPLINE"), sparse=sparse))
    issues = khronos_issues(path)
    bad = [m for m in issues["messages"] if m["severity"] <= 1]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, bad[:5]


def test_many_empty_targets_are_charged_before_they_are_made(tmp_path, monkeypatch):
    """Targets with no data cost the file nothing, but the importer makes dense deltas for each: they
    count against the import's budget before any is allocated."""
    from crowd.asset.gltf import reader

    monkeypatch.setattr(reader, "MAX_DECODED_BYTES", 100_000)
    def many(doc):
        doc["meshes"][0]["primitives"][0]["targets"] = [{} for _ in range(1000)]
        del doc["meshes"][0]["weights"], doc["meshes"][0]["extras"], doc["nodes"][4]["weights"]
        doc["animations"][0]["channels"] = doc["animations"][0]["channels"][:2]
    _hostile(tmp_path, many, "1000 morph targets brings the data read to")


@pytest.mark.parametrize("differ", [False, True])
def test_nodes_sharing_targets_keep_one_channel(tmp_path, differ):
    """A mesh drawn by two nodes (as a piece's LODs share target names), each with its weights channel:
    the same keys are one channel, silently; other keys keep the first, with a warning."""
    def second(doc):
        doc["nodes"].append({"name": "body_copy", "mesh": 0, "skin": 0})
        doc["scenes"][0]["nodes"].append(len(doc["nodes"]) - 1)
        anim = doc["animations"][0]
        sampler = dict(anim["samplers"][2])
        if differ:  # other weights for the same 3 keys of 2 targets
            sampler["output"] = _weights_accessor(doc, np.full(6, 0.5, np.float32))
        anim["samplers"].append(sampler)
        anim["channels"].append({"sampler": len(anim["samplers"]) - 1, "target": {"node": len(doc["nodes"]) - 1, "path": "weights"}})
    c = load_character(_rewrite(make_gltf(tmp_path, morph=True), second), scale=1.0)
    (channel,) = c.clips[0].morph_channels
    assert np.allclose(channel.values, MORPH_KEYS)
    assert any("keys morph targets another weights channel" in w for w in c.warnings) == differ


def _weights_accessor(doc, values) -> int:
    import base64

    blob = bytearray(base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1]))
    while len(blob) % 4:
        blob.append(0)
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": values.nbytes})
    blob += values.tobytes()
    doc["buffers"][0].update(byteLength=len(blob), uri="data:application/octet-stream;base64," + base64.b64encode(bytes(blob)).decode())
    doc["accessors"].append({"bufferView": len(doc["bufferViews"]) - 1, "componentType": 5126, "count": len(values), "type": "SCALAR"})
    return len(doc["accessors"]) - 1


def test_a_coarser_lod_without_targets_takes_its_finer_meshes_by_nearest_vertex(tmp_path):
    """A LOD1 of the strip (the same vertices) that came without targets gets the LOD0's, each vertex the
    deltas of the LOD0 vertex nearest it, with one line saying so (nearest_vertices is checked below)."""
    def lod1(doc):
        prim = {k: v for k, v in doc["meshes"][0]["primitives"][0].items() if k != "targets"}
        doc["meshes"][0]["extras"]["crowd"] = {"piece": "body", "lod": 0}
        doc["meshes"].append({"name": "body_lod1", "primitives": [prim], "extras": {"crowd": {"piece": "body", "lod": 1}}})
        doc["nodes"].append({"name": "body_lod1", "mesh": 1, "skin": 0})
        doc["scenes"][0]["nodes"].append(len(doc["nodes"]) - 1)
    c = load_character(_rewrite(make_gltf(tmp_path, morph=True), lod1), scale=1.0)
    fine, coarse = sorted(c.meshes, key=lambda m: m.lod)
    assert coarse.lod == 1 and coarse.morph_targets.tolist() == fine.morph_targets.tolist()
    assert np.array_equal(coarse.morph_positions, fine.morph_positions)  # the same vertices: each its own
    assert any("body_lod1" in w and "nearest vertex (farthest 0 mm)" in w for w in c.warnings)


def test_nearest_vertices_are_the_nearest():
    from crowd.asset.morph_transfer import nearest_vertices

    rng = np.random.default_rng(2)
    src, pts = rng.normal(size=(300, 3)), rng.normal(size=(500, 3))
    index, dist = nearest_vertices(src, pts)
    brute = np.linalg.norm(pts[:, None] - src[None], axis=2)
    assert np.array_equal(index, np.argmin(brute, axis=1)) and np.allclose(dist, brute.min(axis=1))


def test_targets_of_a_rigid_mesh_on_a_joint_are_left_out_with_a_warning(tmp_path):
    def hat(doc):
        doc["nodes"].append({"name": "hat", "mesh": 0})  # the strip again, rigid, on the tip joint
        doc["nodes"][3].setdefault("children", []).append(len(doc["nodes"]) - 1)
    c = load_character(_rewrite(make_gltf(tmp_path, morph=True), hat), scale=1.0)
    assert any("rigid mesh" in w and "2 morph targets left out" in w for w in c.warnings), c.warnings
