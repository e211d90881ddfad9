"""Compressed glTF (issue 44, point 4). KHR_draco_mesh_compression is decoded by DracoPy (the optional
extra crowd[draco]): a Draco copy of the built-in zombie gives the plain file's vertices within its
position quantisation, and the hostile-file rules hold for the compressed data (one line each).
meshopt compression has its own tests (test_meshopt.py)."""

from __future__ import annotations

import builtins
import importlib
from pathlib import Path

import numpy as np
import pytest

from crowd.asset.gltf import load_character
from crowd.asset.gltf.reader import GltfImportError
from gltf_factory import DRACO_POSITION_BITS, draco_copy, glb_parts, write_glb

pytest.importorskip("DracoPy")
ZOMBIE = importlib.import_module("crowd.asset.zombie").ASSET_PATH


@pytest.fixture(scope="module")
def draco_zombie(tmp_path_factory):
    path = tmp_path_factory.mktemp("draco") / "zombie_draco.glb"
    return path, draco_copy(ZOMBIE, path)


def test_a_draco_copy_gives_the_plain_files_vertices(draco_zombie):
    path, boxes = draco_zombie
    plain, packed = load_character(ZOMBIE, merge=False), load_character(path, merge=False)
    assert [m.name for m in plain.meshes] == [m.name for m in packed.meshes]
    for a, b in zip(plain.meshes, packed.meshes):
        step = boxes[a.name] / (2 ** DRACO_POSITION_BITS - 1)  # the quantisation the copy was written with
        assert np.abs(a.positions - b.positions).max() <= 0.5 * step + 1e-6, a.name
        for field in ("normals", "joints", "weights", "indices", "colors"):
            x, y = getattr(a, field), getattr(b, field)
            assert (x is None and y is None) or np.array_equal(x, y), (a.name, field)
    assert [c.name for c in plain.clips] == [c.name for c in packed.clips]


def _draco_of(doc: dict) -> dict:
    return next(p for m in doc["meshes"] for p in m["primitives"] if "extensions" in p)["extensions"]["KHR_draco_mesh_compression"]


def _broken(tmp_path, draco_zombie, mutate) -> Path:
    doc, blob = glb_parts(draco_zombie[0])
    blob = bytearray(blob)
    mutate(doc, blob)
    return write_glb(tmp_path / "broken.glb", doc, bytes(blob))


def _garbage(doc, blob):
    view = doc["bufferViews"][_draco_of(doc)["bufferView"]]
    blob[view["byteOffset"]: view["byteOffset"] + view["byteLength"]] = bytes(range(256)) * (view["byteLength"] // 256) + \
        bytes(view["byteLength"] % 256)


def _count(doc, blob):
    prim = next(p for m in doc["meshes"] for p in m["primitives"] if "extensions" in p)
    doc["accessors"][prim["attributes"]["POSITION"]]["count"] += 1


@pytest.mark.parametrize("mutate, message", [
    (_garbage, "the Draco data does not decode"),
    (lambda doc, blob: _draco_of(doc)["attributes"].update(POSITION=77), "names Draco attribute 77, which the data does not hold"),
    (lambda doc, blob: _draco_of(doc)["attributes"].update(TEXCOORD_3=0), "compresses TEXCOORD_3, which the primitive's attributes do not name"),
    (_count, "decoded to .* values, the accessor says"),
])
def test_hostile_compressed_data_is_refused_in_one_line(tmp_path, draco_zombie, mutate, message):
    with pytest.raises(GltfImportError, match=message) as info:
        load_character(_broken(tmp_path, draco_zombie, mutate))
    assert "\n" not in str(info.value) and "broken.glb" in str(info.value)


def test_without_dracopy_the_refusal_names_the_extra(draco_zombie, monkeypatch):
    real = builtins.__import__

    def without(name, *args, **kwargs):
        if name == "DracoPy":
            raise ImportError("no DracoPy")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", without)
    with pytest.raises(GltfImportError, match=r"install the optional extra with pip install 'crowd\[draco\]'"):
        load_character(draco_zombie[0])
