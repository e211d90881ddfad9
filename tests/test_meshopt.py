"""meshopt-compressed glTF (EXT_meshopt_compression and KHR_meshopt_compression), decoded by hand in
numpy (crowd.asset.gltf.meshopt): checked against streams and files that meshoptimizer's own encoder
and gltfpack made (tests/data/meshopt/README.md says how), and against hostile streams."""

from __future__ import annotations

import base64
import gzip
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from crowd.asset.gltf import load_character, meshopt, reader
from crowd.asset.gltf.reader import GltfImportError
from crowd.asset.pose import global_matrices, rest_pose, sample_clip
from gltf_factory import glb_parts, write_glb

DATA = Path(__file__).parent / "data" / "meshopt"
ZOMBIE = Path(__file__).parent.parent / "assets" / "zombie.glb"
VECTORS = json.loads(gzip.decompress((DATA / "vectors.json.gz").read_bytes()))["vectors"]
FILTER_TYPE = {"OCTAHEDRAL": {4: "<i1", 8: "<i2"}, "QUATERNION": {8: "<i2"}}
POSITION_BITS = 14  # gltfpack's default position grid, which the fixtures were made with


@pytest.mark.parametrize("vector", VECTORS, ids=[v["name"] for v in VECTORS])
def test_streams_decode_as_meshoptimizer_decodes_them(vector):
    src, want = base64.b64decode(vector["encoded"]), np.frombuffer(base64.b64decode(vector["decoded"]), np.uint8)
    got = np.frombuffer(meshopt.decode(src, vector["count"], vector["stride"], vector["mode"], vector["filter"], khr=True), np.uint8)
    if vector["filter"] in FILTER_TYPE:  # both extensions specify these two filters to one unit in the last place
        dtype = FILTER_TYPE[vector["filter"]][vector["stride"]]
        assert np.abs(got.view(dtype).astype(int) - want.view(dtype).astype(int)).max() <= 1
    else:
        assert np.array_equal(got, want)


def test_the_vectors_reach_every_part_of_the_codecs():
    channel_modes = set()
    for v in VECTORS:
        if v["mode"] == "ATTRIBUTES" and v["version"] == 1:
            channel_modes |= {b & 0xF for b in base64.b64decode(v["encoded"])[-(v["stride"] // 4):]}
    assert channel_modes == {0, 1, 2}
    kinds = {(v["mode"], v["filter"], v["version"], v["stride"] if v["mode"] != "ATTRIBUTES" else None) for v in VECTORS}
    for mode, stride in (("TRIANGLES", 2), ("TRIANGLES", 4), ("INDICES", 2), ("INDICES", 4)):
        assert (mode, "NONE", None, stride) in kinds
    for filt in meshopt.FILTERS:
        assert any(k[1] == filt for k in kinds), filt
    assert {k[2] for k in kinds if k[0] == "ATTRIBUTES"} == {0, 1}


@pytest.mark.parametrize("name", ["zombie_ext.glb", "zombie_khr.glb"])
def test_every_view_of_a_gltfpack_file_decodes_as_meshoptimizer_decodes_it(name):
    """The whole of a real encoder's file, view by view, against meshoptimizer's own decoder."""
    import hashlib

    theirs = json.loads(gzip.decompress((DATA / "zombie_views.json.gz").read_bytes()))["files"][name]
    r = reader.Reader(DATA / name)
    assert len(theirs) == sum("extensions" in v for v in r.doc["bufferViews"]) >= 10
    for view in theirs:
        data, start, length, _ = r.view(view["index"])
        mine = bytes(data[start:start + length])
        if "decoded" in view:
            packed = next(iter(r.doc["bufferViews"][view["index"]]["extensions"].values()))
            dtype = FILTER_TYPE[view["filter"]][packed["byteStride"]]
            want = np.frombuffer(base64.b64decode(view["decoded"]), dtype).astype(int)
            assert np.abs(np.frombuffer(mine, dtype).astype(int) - want).max() <= 1, view
        else:
            assert hashlib.sha256(mine).hexdigest() == view["sha256"], view


def _skinned(character, clip=None, phase=0.0) -> np.ndarray:
    """Every drawn vertex of the character, skinned (float64), at its bind pose or a clip's phase."""
    sk = character.skeleton
    local = rest_pose(sk) if clip is None else sample_clip(sk, character.clips[clip], np.array([phase]))
    palette = global_matrices(sk, local)[0] @ np.asarray(sk.inverse_bind, np.float64)
    out = []
    for mesh in character.meshes:
        used = np.unique(mesh.indices)  # gltfpack drops vertices no triangle uses
        p = np.c_[mesh.positions[used].astype(np.float64), np.ones(len(used))]
        joints, weights = mesh.joints[used], mesh.weights[used].astype(np.float64)
        out.append(sum(weights[:, s:s + 1] * np.einsum("vab,vb->va", palette[joints[:, s]], p)[:, :3]
                       for s in range(joints.shape[1])))
    return np.concatenate(out)


def _farthest(a: np.ndarray, b: np.ndarray) -> float:
    """The largest distance from a point of `a` to the nearest point of `b`."""
    near = np.full(len(a), np.inf)
    for i in range(0, len(b), 1024):
        near = np.minimum(near, np.linalg.norm(a[:, None] - b[None, i:i + 1024], axis=2).min(axis=1))
    return float(near.max())


@pytest.fixture(scope="module")
def plain():
    return load_character(ZOMBIE, merge=False)


@pytest.mark.parametrize("name", ["zombie_ext.glb", "zombie_khr.glb"])
def test_a_gltfpack_copy_of_the_zombie_draws_its_vertices(plain, name):
    packed = load_character(DATA / name, merge=False)
    assert [c.name for c in packed.clips] == [c.name for c in plain.clips]
    assert sorted(len(np.unique(m.indices)) for m in packed.meshes) == sorted(len(np.unique(m.indices)) for m in plain.meshes)
    a, b = _skinned(plain), _skinned(packed)
    step = (a.max(0) - a.min(0)).max() / (2 ** POSITION_BITS - 1)  # the grid gltfpack put the positions on
    assert _farthest(a, b) <= step and _farthest(b, a) <= step
    for clip, phase in ((0, 0.3), (1, 0.55), (3, 0.7), (5, 0.9)):
        # gltfpack resamples clips and rounds their rotations to 12 bits: measured 0.41 to 0.63 mm here
        assert _farthest(_skinned(plain, clip, phase), _skinned(packed, clip, phase)) < 1e-3


# -- hostile files: each a one-line refusal naming the file and the bufferView


def _packed(doc: dict, mode: str = "ATTRIBUTES", ext: str = "EXT_meshopt_compression") -> dict:
    return next(v["extensions"][ext] for v in doc["bufferViews"] if v.get("extensions", {}).get(ext, {}).get("mode") == mode)


def _garble(doc, blob):
    e = _packed(doc)
    blob[e["byteOffset"] + 1:e["byteOffset"] + e["byteLength"]] = b"\xff" * (e["byteLength"] - 1)


def _header(doc, blob):
    blob[_packed(doc)["byteOffset"]] = 0x55


def _shorter(doc, blob):
    _packed(doc)["byteLength"] -= 7


def _triangle_fifo(doc, blob):
    blob[_packed(doc, "TRIANGLES")["byteOffset"] + 1] = 0x50  # the first triangle reads an edge never written


def _both(doc, blob):
    view = next(v for v in doc["bufferViews"] if "extensions" in v)
    view["extensions"]["KHR_meshopt_compression"] = view["extensions"]["EXT_meshopt_compression"]


def _huge(doc, blob):
    view = next(v for v in doc["bufferViews"] if "extensions" in v)
    e = view["extensions"]["EXT_meshopt_compression"]
    e["count"] = 1 << 40
    view["byteLength"] = e["count"] * e["byteStride"]
    doc["buffers"][view["buffer"]]["byteLength"] = view["byteLength"]


@pytest.mark.parametrize("mutate, message", [
    (_garble, r"bufferView \d+ EXT_meshopt_compression: (runs out of data|leaves \d+ bytes unread)"),
    (_header, "is not an ATTRIBUTES stream"),
    (_shorter, "runs out of data|leaves|too few"),
    (_triangle_fifo, "reads edge FIFO entry 5 before it was written, at triangle 0"),
    (lambda doc, blob: _packed(doc).update(count=_packed(doc)["count"] + 1), "is not the bufferView's byteLength"),
    (lambda doc, blob: _packed(doc).update(mode="STRIPS"), "mode must be one of ATTRIBUTES, TRIANGLES, INDICES"),
    (lambda doc, blob: _packed(doc).update(filter="COLOR"), "filter must be one of NONE, OCTAHEDRAL, QUATERNION, EXPONENTIAL, got 'COLOR'"),
    (lambda doc, blob: _packed(doc, "TRIANGLES").update(byteStride=8), "byteStride 8 of TRIANGLES must be 2 or 4"),
    (lambda doc, blob: _packed(doc).update(buffer=9), "buffer"),
    (lambda doc, blob: _packed(doc).update(byteOffset=10 ** 9), "runs past the end of buffer"),
    (_both, "uses both EXT_meshopt_compression and KHR_meshopt_compression"),
    (_huge, "more than the"),
])
def test_hostile_meshopt_data_is_refused_in_one_line(tmp_path, mutate, message):
    doc, blob = glb_parts(DATA / "zombie_ext.glb")
    blob = bytearray(blob)
    mutate(doc, blob)
    with pytest.raises(GltfImportError, match=message) as info:
        load_character(write_glb(tmp_path / "broken.glb", doc, blob))
    assert "\n" not in str(info.value) and str(info.value).startswith("broken.glb: ")


def test_version_1_streams_need_the_khr_extension(tmp_path):
    doc, blob = glb_parts(DATA / "zombie_khr.glb")
    text = json.dumps(doc).replace("KHR_meshopt_compression", "EXT_meshopt_compression")
    with pytest.raises(GltfImportError, match="version 1 of the attribute codec, which only KHR_meshopt_compression allows"):
        load_character(write_glb(tmp_path / "renamed.glb", json.loads(text), blob))


def test_the_decoding_budget_bounds_the_time(tmp_path, monkeypatch):
    monkeypatch.setattr(reader, "MAX_MESHOPT_BYTES", 20_000)
    with pytest.raises(GltfImportError, match=r"brings the meshopt data decoded to [\d,]+ bytes .* more than the 20,000 allowed"):
        load_character(DATA / "zombie_ext.glb")


@settings(max_examples=300, deadline=None)
@given(data=st.binary(max_size=400), count=st.integers(1, 200), stride=st.sampled_from([2, 4, 8, 12, 64, 256]),
       mode=st.sampled_from(meshopt.MODES), filt=st.sampled_from(meshopt.FILTERS), khr=st.booleans())
def test_any_bytes_decode_or_raise_one_clear_error(data, count, stride, mode, filt, khr):
    if mode != "ATTRIBUTES":
        stride, filt = (2 if stride == 2 else 4), "NONE"
        count = max(3, count - count % 3)
    try:
        meshopt.check_layout(meshopt.EXTENSIONS[khr], count, stride, mode, filt, count * stride)
    except meshopt.MeshoptError:
        filt = "NONE"
    header = {"ATTRIBUTES": bytes([0xA1 if khr else 0xA0]), "TRIANGLES": b"\xe1", "INDICES": b"\xd1"}[mode]
    for src in (data, header + data):
        try:
            out = meshopt.decode(src, count, stride, mode, filt, khr)
        except meshopt.MeshoptError as exc:
            assert "\n" not in str(exc)
        else:
            assert len(out) == count * stride


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_flipped_bytes_in_real_streams_decode_or_raise_one_clear_error(data):
    vector = data.draw(st.sampled_from(VECTORS))
    src = bytearray(base64.b64decode(vector["encoded"]))
    for _ in range(data.draw(st.integers(1, 4))):
        src[data.draw(st.integers(0, len(src) - 1))] = data.draw(st.integers(0, 255))
    try:
        out = meshopt.decode(bytes(src), vector["count"], vector["stride"], vector["mode"], vector["filter"], True)
    except meshopt.MeshoptError as exc:
        assert "\n" not in str(exc)
    else:
        assert len(out) == vector["count"] * vector["stride"]
