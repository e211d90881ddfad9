"""Hostile glTF files (issue 18, point 4): each is refused in one line naming the file, the element and
its index, or repaired with a named warning; nothing reads outside its buffers, allocates without
bound or hands the stages a value they cannot draw. Every command that takes --model answers a bad
file with one line and exit 2."""

import json
import os
import struct
import subprocess
import sys
import time
import tracemalloc

import numpy as np
import pytest

from conftest import ROOT, shared
from crowd.asset import gltf
from crowd.asset.gltf import reader
from crowd.asset.gltf import load_character
from crowd.asset.gltf.reader import GltfImportError
from crowd.asset.model import vertex_normals
from crowd.asset.zombie import ASSET_PATH
import gltf_factory
from gltf_factory import make_gltf, write_glb


# -- building hostile files

def _attribute(doc, name):
    return doc["meshes"][0]["primitives"][0]["attributes"][name]


def _sampler(doc, path):
    anim = doc["animations"][0]
    return anim["samplers"][next(c["sampler"] for c in anim["channels"] if c["target"]["path"] == path)]


def _write(doc, blob, accessor, values):
    """Overwrite an accessor's bytes (the factory packs each accessor in a view of its own)."""
    view = doc["bufferViews"][doc["accessors"][accessor]["bufferView"]]
    data = np.asarray(values, np.float32).tobytes()
    assert len(data) <= view["byteLength"]
    blob[view["byteOffset"]: view["byteOffset"] + len(data)] = data


def _read(doc, blob, accessor, dtype=np.float32):
    acc = doc["accessors"][accessor]
    view = doc["bufferViews"][acc["bufferView"]]
    return np.frombuffer(bytes(blob[view["byteOffset"]: view["byteOffset"] + view["byteLength"]]), dtype).copy()


def hostile(tmp_path, mutate, **options):
    """The factory's character with an external buffer, after mutate(doc, blob)."""
    path = make_gltf(tmp_path, buffer_mode="external", **options)
    doc = json.loads(path.read_text())
    blob = bytearray((tmp_path / "test.bin").read_bytes())
    mutate(doc, blob)
    path.write_text(json.dumps(doc))
    (tmp_path / "test.bin").write_bytes(bytes(blob))
    return path


def glb_parts(path=ASSET_PATH):
    return gltf_factory.glb_parts(path)


def refused(path, *needles):
    with pytest.raises(GltfImportError) as info:
        load_character(path)
    message = str(info.value)
    assert "\n" not in message and message.startswith(path.name + ":"), message
    assert gltf._UNEXPECTED not in message, message  # the safety net caught it: a check is missing
    for needle in needles:
        assert needle in message, message
    return message


# -- the cases issue 18 lists

def test_negative_accessor_byte_offset_is_refused(tmp_path):
    path = hostile(tmp_path, lambda d, b: d["accessors"][_attribute(d, "POSITION")].update(byteOffset=-64))
    refused(path, "accessor 0 (body POSITION)", "byteOffset", "-64")


def test_negative_buffer_view_byte_offset_is_refused(tmp_path):
    path = hostile(tmp_path, lambda d, b: d["bufferViews"][0].update(byteOffset=-64))
    refused(path, "bufferView 0", "byteOffset", "-64")


def test_negative_byte_offset_in_the_zombie_reads_nothing_it_does_not_own(tmp_path):
    # Past the start of the buffer by a little: today's reader walked off the end of the view.
    doc, blob = glb_parts()
    doc["accessors"][1]["byteOffset"] = -12
    refused(write_glb(tmp_path / "zombie.glb", doc, blob), "accessor 1", "byteOffset")


def test_negative_count_is_refused(tmp_path):
    path = hostile(tmp_path, lambda d, b: d["accessors"][_attribute(d, "POSITION")].update(count=-3))
    refused(path, "accessor 0", "count", "-3")


def test_missing_buffer_view_byte_length_is_refused(tmp_path):
    path = hostile(tmp_path, lambda d, b: d["bufferViews"][0].pop("byteLength"))
    refused(path, "bufferView 0 has no byteLength")


def test_translation_with_two_values_is_refused(tmp_path):
    path = hostile(tmp_path, lambda d, b: d["nodes"][2].update(translation=[0.0, 1.0]))
    refused(path, "node 2 ('mid'): translation must be 3 numbers")


def test_huge_accessor_without_buffer_view_is_refused_before_allocating(tmp_path):
    def mutate(d, b):
        acc = d["accessors"][d["skins"][0]["inverseBindMatrices"]]
        acc.pop("bufferView")
        acc["count"] = 400_000_000
    path = hostile(tmp_path, mutate)
    tracemalloc.start()
    try:
        refused(path, "inverseBindMatrices", "400,000,000", "more than")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 << 20  # refused from the header, not after allocating 25 GB


def test_position_accessor_without_data_is_refused(tmp_path):
    # What a Draco file looks like to a reader without Draco: an accessor of zeros.
    def mutate(d, b):
        acc = d["accessors"][_attribute(d, "POSITION")]
        acc.pop("bufferView")
    refused(hostile(tmp_path, mutate), "accessor 0 (body POSITION) has no data")


def test_huge_key_times_are_refused_in_the_importer(tmp_path):
    def mutate(d, b):
        times = _sampler(d, "rotation")["input"]
        _write(d, b, times, _read(d, b, times) * np.float32(1e30))
    refused(hostile(tmp_path, mutate), "animation 'wave' lasts 1e+30 s", "3600")


@pytest.mark.parametrize("times, needle", [
    ([0.5, np.nan, 1.5], "key 1 is NaN or infinite"),
    ([-0.5, 1.0, 1.5], "key 0 is at -0.5 s"),
    ([0.5, 1.0, 1.0], "key times do not increase (key 2"),
])
def test_bad_key_times_are_refused(tmp_path, times, needle):
    path = hostile(tmp_path, lambda d, b: _write(d, b, _sampler(d, "rotation")["input"], times))
    refused(path, "accessor", "key times of animation 'wave'", needle)


def test_zero_rotation_keys_are_refused(tmp_path):
    def mutate(d, b):
        out = _sampler(d, "rotation")["output"]
        keys = _read(d, b, out).reshape(-1, 4)
        keys[1] = 0.0
        _write(d, b, out, keys)
    message = refused(hostile(tmp_path, mutate), "(rotation keys of animation 'wave' channel 0): key 1 is the zero quaternion")
    assert message.startswith("test.gltf: accessor ")


def test_cubic_rotation_through_zero_is_refused(tmp_path):
    # Keys q and -q with flat tangents: the spline is zero half way, and glTF normalises after evaluating.
    def mutate(d, b):
        out = _sampler(d, "rotation")["output"]
        keys = _read(d, b, out).reshape(-1, 3, 4)
        keys[1, 1] = -keys[0, 1]
        _write(d, b, out, keys)
    refused(hostile(tmp_path, mutate, interpolation="CUBICSPLINE"), "between keys 0 and 1 passes through the zero quaternion")


def test_unnormalised_rotation_keys_are_normalised(tmp_path):
    def mutate(d, b):
        out = _sampler(d, "rotation")["output"]
        _write(d, b, out, _read(d, b, out) * 3.0)
    c = load_character(hostile(tmp_path, mutate))
    rot = next(ch for ch in c.clips[0].channels if ch.path == "rotation")
    np.testing.assert_allclose(np.linalg.norm(rot.values, axis=1), 1.0, atol=1e-12)


def test_huge_translation_keys_are_refused(tmp_path):
    def mutate(d, b):
        out = _sampler(d, "translation")["output"]
        keys = _read(d, b, out).reshape(-1, 3)
        keys[2] = 1e30
        _write(d, b, out, keys)
    refused(hostile(tmp_path, mutate), "(translation keys of animation 'wave' channel 1): key 2 lies beyond ±1e+06")


def test_huge_node_translation_is_refused(tmp_path):
    path = hostile(tmp_path, lambda d, b: d["nodes"][2].update(translation=[0.0, 1e30, 0.0]))
    refused(path, "node 2 ('mid'): translation", "beyond ±1e+06")


def test_nan_node_values_are_refused(tmp_path):
    path = hostile(tmp_path, lambda d, b: d["nodes"][3].update(scale=[1.0, float("nan"), 1.0]))
    refused(path, "node 3 ('tip'): scale holds NaN or infinity")


def test_scales_multiplying_down_a_chain_are_refused(tmp_path):
    def mutate(d, b):
        for n in (1, 2, 3):
            d["nodes"][n]["scale"] = [500.0, 500.0, 500.0]
    refused(hostile(tmp_path, mutate), "joint 'tip': the scales down its chain multiply to 1.25e+08")


def test_nan_normals_are_recomputed_with_a_warning(tmp_path):
    def mutate(d, b):
        _write(d, b, _attribute(d, "NORMAL"), np.full((6, 3), np.nan))
    c = load_character(hostile(tmp_path, mutate))
    assert "body: 6 normals were NaN, infinite or zero length; recomputed from the triangles" in c.warnings
    m = c.meshes[0]
    expected = vertex_normals(m.positions.astype(np.float64), m.indices.astype(np.int64))
    np.testing.assert_allclose(m.normals, expected, atol=1e-6)


def test_zero_length_normals_are_recomputed_and_the_others_kept(tmp_path):
    def mutate(d, b):
        normals = np.tile([[0.0, 0.0, 1.0]], (6, 1))
        normals[4] = 0.0
        _write(d, b, _attribute(d, "NORMAL"), normals)
    c = load_character(hostile(tmp_path, mutate))
    assert any("1 normals were NaN, infinite or zero length" in w for w in c.warnings)
    n = c.meshes[0].normals
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(n[[0, 1, 2, 3, 5]], np.tile([[0, 0, 1]], (5, 1)))


def test_zero_quaternion_rest_rotation_becomes_the_identity_with_a_warning(tmp_path):
    c = load_character(hostile(tmp_path, lambda d, b: d["nodes"][2].update(rotation=[0, 0, 0, 0])))
    assert "node 2 ('mid'): rotation is the zero quaternion; used the identity" in c.warnings
    np.testing.assert_array_equal(c.skeleton.rest_rotation[1], [0, 0, 0, 1])


# -- accessors, bufferViews, buffers

@pytest.mark.parametrize("mutate, needle", [
    (lambda d, b: d["bufferViews"][0].update(byteLength=10**6), "bufferView 0 runs past the end of buffer 0"),
    (lambda d, b: d["bufferViews"][0].update(byteStride=2), "byteStride must be a whole number from 4 to 252, got 2"),
    (lambda d, b: d["bufferViews"][0].update(byteStride=256), "byteStride must be a whole number from 4 to 252"),
    (lambda d, b: d["bufferViews"][0].update(byteStride=8), "byteStride 8 is smaller than an element (12 bytes)"),
    (lambda d, b: d["bufferViews"][0].update(buffer=3), "bufferView 0: buffer 3 is out of range"),
    (lambda d, b: d["accessors"][0].update(byteOffset=64), "accessor 0 (body POSITION) reads 136 bytes from bufferView 0 of 72"),
    (lambda d, b: d["accessors"][0].update(count=2**62), "more than the"),
    (lambda d, b: d["accessors"][0].update(count="6"), "count must be a whole number of at least 1, got '6'"),
    (lambda d, b: d["accessors"][0].update(count=6.5), "count must be a whole number"),
    (lambda d, b: d["accessors"][0].update(type="VEC2"), "accessor 0 (body POSITION) must be VEC3, got VEC2"),
    (lambda d, b: d["accessors"][0].update(type=3), "unknown type 3"),
    (lambda d, b: d["accessors"][0].update(normalized=True), "is float and normalized, which glTF forbids"),
    (lambda d, b: d["accessors"][_attribute(d, "JOINTS_0")].update(componentType=5126), "must have componentType UNSIGNED_BYTE or"),
    (lambda d, b: d["accessors"][d["meshes"][0]["primitives"][0]["indices"]].update(componentType=5122), "indices) must have componentType"),
    (lambda d, b: d["accessors"][_attribute(d, "NORMAL")].update(count=5), "has 5 elements for 6 vertices"),
    (lambda d, b: d["buffers"][0].pop("byteLength"), "buffer 0 has no byteLength"),
    (lambda d, b: d["buffers"][0].update(uri="/etc/passwd"), "points outside the file's folder"),
    (lambda d, b: d["buffers"][0].update(uri="a\u0000b.bin"), "is not a usable path"),
    (lambda d, b: d["buffers"][0].update(uri="data:application/octet-stream,AAAA"), "malformed data URI"),
    (lambda d, b: d["buffers"][0].update(uri=7), "buffer 0: uri must be a string, got 7"),
    (lambda d, b: d.update(extensionsRequired=["EXT_mesh_gpu_instancing"]), "requires extension 'EXT_mesh_gpu_instancing'"),
])
def test_accessor_view_and_buffer_rules(tmp_path, mutate, needle):
    refused(hostile(tmp_path, mutate), needle)


def test_buffer_file_that_is_not_a_regular_file_is_refused_without_blocking(tmp_path):
    path = hostile(tmp_path, lambda d, b: d["buffers"][0].update(uri="fifo.bin"))
    os.mkfifo(tmp_path / "fifo.bin")  # reading it would block for ever
    refused(path, "buffer 0 file 'fifo.bin' is not a regular file")


@pytest.mark.parametrize("mutate, needle", [
    (lambda s: s.update(count=7), "count must be a whole number from 1 to 6"),
    (lambda s: s["indices"].update(componentType=5126), "sparse indices have componentType 5126"),
    (lambda s: s["indices"].update(byteOffset=-2), "byteOffset must be a whole number of at least 0"),
    (lambda s: s.pop("values"), "sparse has no values"),
])
def test_sparse_accessor_rules(tmp_path, mutate, needle):
    def m(d, b):
        mutate(d["accessors"][_attribute(d, "POSITION")]["sparse"])
    refused(hostile(tmp_path, m, sparse=True), needle)


@pytest.mark.parametrize("indices, needle", [([0, 1, 2, 3, 4, 9], "index 9 points past the accessor's 6 elements"),
                                             ([0, 1, 3, 2, 4, 5], "indices must increase strictly")])
def test_sparse_indices_are_checked(tmp_path, indices, needle):
    def m(d, b):
        sparse = d["accessors"][_attribute(d, "POSITION")]["sparse"]
        view = d["bufferViews"][sparse["indices"]["bufferView"]]
        b[view["byteOffset"]: view["byteOffset"] + 12] = np.array(indices, np.uint16).tobytes()
    refused(hostile(tmp_path, m, sparse=True), needle)


def test_memory_budget_over_all_accessor_reads(tmp_path, monkeypatch):
    monkeypatch.setattr(reader, "MAX_DECODED_BYTES", 1000)
    refused(make_gltf(tmp_path), "brings the data read to", "more than the 1,000 allowed")


def test_file_budget_and_json_budget(tmp_path, monkeypatch):
    path = make_gltf(tmp_path, buffer_mode="external")
    monkeypatch.setattr(reader, "MAX_FILE_BYTES", path.stat().st_size + 100)
    refused(path, "buffer 0 file 'test.bin' would bring the bytes read to")
    monkeypatch.setattr(reader, "MAX_FILE_BYTES", 1 << 30)
    monkeypatch.setattr(reader, "MAX_JSON_VALUES", 50)
    refused(path, "the JSON holds about", "more than the 50 allowed")


# -- meshes

@pytest.mark.parametrize("mutate, needle", [
    (lambda d, b: _write(d, b, _attribute(d, "POSITION"), np.where(np.arange(18) == 7, np.nan, 0.5)), "(body POSITION): vertex 2 is NaN or infinite"),
    (lambda d, b: _write(d, b, _attribute(d, "POSITION"), np.where(np.arange(18) == 13, 2e6, 0.5)), "(body POSITION): vertex 4 lies beyond ±1e+06"),
    (lambda d, b: _write(d, b, _attribute(d, "WEIGHTS_0"), np.where(np.arange(24) == 9, np.inf, 0.25)), "(body WEIGHTS_0): vertex 2 has a NaN or infinite weight"),
    (lambda d, b: _write(d, b, _attribute(d, "WEIGHTS_0"), np.where(np.arange(24) == 20, -0.5, 0.25)), "(body WEIGHTS_0): vertex 5 has a negative weight (-0.5)"),
])
def test_vertex_values_that_cannot_be_drawn_are_refused(tmp_path, mutate, needle):
    refused(hostile(tmp_path, mutate), needle)


def test_index_past_the_vertices_is_refused(tmp_path):
    def mutate(d, b):
        view = d["bufferViews"][d["accessors"][d["meshes"][0]["primitives"][0]["indices"]]["bufferView"]]
        b[view["byteOffset"] + 8: view["byteOffset"] + 10] = np.uint16(60000).tobytes()
    refused(hostile(tmp_path, mutate), "body has an index past its 6 vertices (index 4 is 60000)")


def test_joint_index_past_the_skin_is_refused(tmp_path):
    def mutate(d, b):
        view = d["bufferViews"][d["accessors"][_attribute(d, "JOINTS_0")]["bufferView"]]
        b[view["byteOffset"] + 8] = 7  # vertex 2, first influence (weight 0.5)
    refused(hostile(tmp_path, mutate), "body references joint 7 but the skin has 3 (vertex 2)")


def test_nan_colours_and_base_colour_are_refused(tmp_path):
    path = hostile(tmp_path, lambda d, b: (d.update(materials=[{"pbrMetallicRoughness": {"baseColorFactor": [1, 1, float("nan"), 1]}}]),
                                           d["meshes"][0]["primitives"][0].update(material=0)))
    refused(path, "material 0 pbrMetallicRoughness: baseColorFactor holds NaN or infinity")


@pytest.mark.parametrize("extras, needle", [
    ({"lod": "x"}, "extras.crowd.lod must be a whole number from 0 to 15, got 'x'"),
    ({"lod": 10**9}, "extras.crowd.lod must be a whole number from 0 to 15"),
])
def test_mesh_extras_are_checked(tmp_path, extras, needle):
    refused(hostile(tmp_path, lambda d, b: d["meshes"][0].update(extras={"crowd": extras})), needle)


@pytest.mark.parametrize("extras, needle", [
    ({"stride": float("nan")}, "extras.crowd.stride must be a length"),
    ({"stride": -1}, "extras.crowd.stride must be a length"),
    ({"markers": {"left_foot_down": "x"}}, "extras.crowd.markers must map names to phases"),
    ({"markers": {"left_foot_down": 1.5}}, "marker 'left_foot_down' phase 1.5 is outside [0, 1)"),
])
def test_clip_extras_are_checked(tmp_path, extras, needle):
    refused(hostile(tmp_path, lambda d, b: d["animations"][0].update(extras={"crowd": extras})), needle)


# -- structure and JSON types

@pytest.mark.parametrize("mutate, needle", [
    (lambda d, b: d.update(nodes={"a": 1}), "'nodes' must be an array"),
    (lambda d, b: d["nodes"].__setitem__(3, None), "node 3 is not a JSON object"),
    (lambda d, b: d["nodes"][0].update(children=5), "node 0 ('Armature'): children must be an array"),
    (lambda d, b: d["nodes"][0].update(children=[True]), "node 0 has child True out of range"),
    (lambda d, b: d["nodes"][4].update(mesh=True), "node 4 ('body'): mesh True is out of range"),
    (lambda d, b: d["nodes"][2].update(matrix=[1, 0, 0]), "node 2 ('mid'): matrix must be 16 numbers"),
    (lambda d, b: d["nodes"][2].update(matrix=[1, 0, 0, 0.5, 0, 1, 0, 0, 0, 0, 1, 0, 0, 1, 0, 1]), "matrix is not affine"),
    (lambda d, b: d["skins"][0].update(joints=[1, 2, "3"]), "joint node index '3' is out of range"),
    (lambda d, b: d["skins"][0].update(joints=[1, 2, [3]]), "joint node index [3] is out of range"),
    (lambda d, b: d["accessors"].__setitem__(0, 5), "accessor 0 is not a JSON object"),
    (lambda d, b: d["meshes"][0]["primitives"][0].update(attributes=5), "attributes must be a JSON object"),
    (lambda d, b: d["meshes"][0]["primitives"][0].update(mode="x"), "mode must be a whole number from 0 to 6"),
    (lambda d, b: d["animations"][0]["channels"][0].update(sampler=9), "sampler index 9 is out of range"),
    (lambda d, b: d["animations"][0]["channels"][0]["target"].update(node=99), "target: node 99 is out of range"),
    (lambda d, b: d["animations"][0]["samplers"][0].update(input=None), "has no input"),
    (lambda d, b: d["animations"][0]["samplers"][0].update(output=1), "(rotation keys of animation 'wave' channel 0) must be VEC4, got VEC3"),
    (lambda d, b: d.update(asset=5), "glTF version is missing"),
    (lambda d, b: d.pop("animations"), "no clips, and the built-in clips cannot be retargeted to it: no joint found for hips"),
    (lambda d, b: d.update(extensionsRequired="KHR_draco_mesh_compression"), "extensionsRequired must be an array"),
])
def test_wrong_json_types_and_indices_are_refused(tmp_path, mutate, needle):
    refused(hostile(tmp_path, mutate), needle)


def test_unknown_target_path_is_left_out_with_a_warning(tmp_path):
    def mutate(d, b):
        d["animations"][0]["channels"].append({"sampler": 0, "target": {"node": 2, "path": "pointer"}})
    c = load_character(hostile(tmp_path, mutate))
    assert "animation 'wave' channel 2: target path 'pointer' is not a joint transform; left out" in c.warnings


@pytest.mark.parametrize("cut", [5, 13, 24, 400])
def test_truncated_or_garbled_glb_container_is_refused(tmp_path, cut):
    data = ASSET_PATH.read_bytes()
    bad = tmp_path / "zombie.glb"
    bad.write_bytes(data[:cut])
    refused(bad)


@pytest.mark.parametrize("patch, needle", [
    (lambda d: d[:4] + struct.pack("<I", 1) + d[8:], "GLB container version 1 is not 2"),
    (lambda d: d[:8] + struct.pack("<I", len(d) + 4) + d[12:], "GLB header says"),
    (lambda d: d[:12] + struct.pack("<I", 2**31) + d[16:], "GLB chunk 0 runs past the end of the file"),
    (lambda d: d[:16] + b"BIN\x00" + d[20:], "the first GLB chunk is not JSON"),
])
def test_glb_header_and_chunk_rules(tmp_path, patch, needle):
    bad = tmp_path / "zombie.glb"
    bad.write_bytes(patch(ASSET_PATH.read_bytes()))
    refused(bad, needle)


def test_deep_hierarchies_import_in_linear_time(tmp_path):
    # 30,000 non-joint nodes above the armature and a 2,000-joint tail: quadratic walks would take minutes.
    def mutate(d, b):
        nodes = d["nodes"]
        first = len(nodes)
        chain = [{"name": f"group{i}", "children": [first + i + 1]} for i in range(30_000)]
        chain[-1]["children"] = [0]
        nodes.extend(chain)
        tail_first = len(nodes)
        nodes[3]["children"] = [tail_first]
        nodes.extend({"name": f"tail{i}", "translation": [0, 0.001, 0], "children": [tail_first + i + 1]} for i in range(2000))
        del nodes[-1]["children"]
        d["skins"][0]["joints"] += list(range(tail_first, tail_first + 2000))
        d["skins"][0].pop("inverseBindMatrices")
        d["scenes"][0]["nodes"] = [first, 4]
    t0 = time.perf_counter()
    c = load_character(hostile(tmp_path, mutate))
    assert c.skeleton.joint_count == 2003 and time.perf_counter() - t0 < 10.0


def test_cycles_are_still_found(tmp_path):
    refused(hostile(tmp_path, lambda d, b: d["nodes"][3].update(children=[1])), "node 1 has two parents")
    refused(hostile(tmp_path, lambda d, b: (d["nodes"][0].update(children=[]), d["nodes"][3].update(children=[1]))),
            "node hierarchy has a cycle through node 1")


def test_shared_cesium_man_survives_a_negative_offset_into_its_interleaved_views(tmp_path):
    doc, blob = glb_parts(shared("CesiumMan.glb"))
    strided = next(i for i, a in enumerate(doc["accessors"]) if doc["bufferViews"][a.get("bufferView", 0)].get("byteStride"))
    doc["accessors"][strided]["byteOffset"] = -4
    refused(write_glb(tmp_path / "CesiumMan.glb", doc, blob), f"accessor {strided}", "byteOffset")


# -- every command that takes --model: one line, exit 2

BAD_MODEL_COMMANDS = {
    "crowd-demo": ["-m", "app.demo", "--headless", "--frames", "1", "--agents", "4", "--size", "64x64"],
    "crowd-bench bake": ["-m", "bench", "bake", "--rates", "30", "--samples", "3"],
    "crowd-bench scale": ["-m", "bench", "scale", "--agents", "16", "--frames", "1", "--size", "64x64"],
    "crowd-bench ai": ["-m", "bench", "ai", "--agents", "10", "--steps", "1", "--warmup", "0"],
    "crowd-bench error": ["-m", "bench", "error"],
    "crowd-bench peers": ["-m", "bench", "peers", "--systems", "crowd"],
    "bench.preview": ["-m", "bench.preview", "preview.png"],
}


@pytest.fixture(scope="module")
def bad_model(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bad_model")
    return hostile(folder, lambda d, b: d["accessors"][_attribute(d, "POSITION")].update(byteOffset=-64))


@pytest.mark.parametrize("command", list(BAD_MODEL_COMMANDS))
def test_every_model_command_answers_a_bad_file_in_one_line(command, bad_model, tmp_path):
    args = BAD_MODEL_COMMANDS[command] + ["--model", str(bad_model)]
    if command == "crowd-bench peers":
        args += ["--screenshots", str(tmp_path / "peers")]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=120, cwd=tmp_path, env=env)
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr + r.stdout, r.stderr
    assert "test.gltf: accessor 0 (body POSITION): byteOffset must be a whole number of at least 0, got -64" in lines[0]


def test_singular_prop_grip_is_refused(tmp_path):
    # The weapons stage draws a prop through inverse(grip): a zero-scale grip would raise there.
    doc, blob = glb_parts()
    grip = next(i for i, n in enumerate(doc["nodes"]) if n.get("extras", {}).get("crowd", {}).get("grip") is not None)
    doc["nodes"][grip]["scale"] = [0.0, 0.0, 0.0]
    refused(write_glb(tmp_path / "zombie.glb", doc, blob), f"node {grip} ('weapon_pipe_grip') (grip of prop 'pipe'): the matrix is singular")


def _prop_lod_node(doc, prop: str, lod: int) -> int:
    return next(i for i, n in enumerate(doc["nodes"]) if n.get("extras", {}).get("crowd", {}) == {"prop": prop, "lod": lod})


def test_a_bad_prop_lod_is_refused_and_a_lone_one_left_out(tmp_path):
    doc, blob = glb_parts()
    node = _prop_lod_node(doc, "pipe", 1)
    doc["nodes"][node]["extras"]["crowd"]["lod"] = "x"
    refused(write_glb(tmp_path / "zombie.glb", doc, blob), f"node {node} ('weapon_pipe_lod1'): extras.crowd.lod must be a whole number from 0 to 15, got 'x'")
    # Coarser meshes of a prop the file has no LOD0 mesh for: a warning, the other props kept.
    doc, blob = glb_parts()
    for k in (1, 2, 3):
        doc["nodes"][_prop_lod_node(doc, "axe", k)]["extras"]["crowd"]["prop"] = "hammer"
    # A gap (LOD2 missing): LOD1's mesh serves it.
    gap, last = _prop_lod_node(doc, "pipe", 2), _prop_lod_node(doc, "pipe", 3)
    doc["nodes"][last]["extras"]["crowd"]["prop"] = "spare"
    doc["nodes"][gap]["extras"]["crowd"]["lod"] = 3
    c = load_character(write_glb(tmp_path / "zombie.glb", doc, blob))
    assert any("prop 'hammer': coarser LOD meshes but no LOD0 mesh; left out" in w for w in c.warnings)
    assert any("prop 'spare'" in w for w in c.warnings)
    assert set(c.props) == {"pipe", "axe"} and len(c.props["axe"].lods) == 1
    pipe = c.props["pipe"].lods
    assert len(pipe) == 4 and pipe[2] is pipe[1] and pipe[3].name == "weapon_pipe_lod2"


@pytest.mark.parametrize("matrix, needle", [
    (lambda m: m.__setitem__((1, 0, 1), np.nan), "(inverseBindMatrices): matrix 1 holds NaN or infinity"),
    (lambda m: m.__setitem__((2, 3, 0), 0.5), "(inverseBindMatrices): matrix 2 is not affine"),
    (lambda m: m.__setitem__((0, slice(0, 3), 0), 0.0), "(inverseBindMatrices): matrix 0 is singular"),
    (lambda m: m.__setitem__((0, 0, 3), 1e7), "(inverseBindMatrices): matrix 0 holds a value beyond ±1e+06"),
])
def test_inverse_bind_matrices_are_checked(tmp_path, matrix, needle):
    def mutate(d, b):
        acc = d["skins"][0]["inverseBindMatrices"]
        m = _read(d, b, acc).reshape(3, 4, 4)  # column-major: m[k, column, row]
        matrix(m.transpose(0, 2, 1))  # row-major view: [k, row, column]
        _write(d, b, acc, m)
    refused(hostile(tmp_path, mutate), needle)
