"""Property-based fuzzing of the importer (issue 18, point 4).

Mutants of the built-in zombie, of the third-party samples in ../shared/gltf (when present) and of a file with
morph targets (the test strip, written sparse by the project's writer), made at
the JSON level (numbers in accessors, bufferViews, buffers, nodes, skins, meshes and animations made
negative, huge, NaN or of the wrong type; keys removed; indices out of range; array elements swapped
or dropped) and at the byte level (bits flipped, ranges zeroed or garbled inside a bufferView, the
binary or the whole file cut short). For each mutant, either
- ``load_character`` raises ``GltfImportError`` with one line that starts with the file's name (and
  not the importer's safety net, which would mean a check is missing), or
- it returns a Character whose meshes are finite and whose float64 palette (``reference_palette`` on
  the bake of every clip, at a few phases, for every interpolation, the rest-pose fallback included)
  is finite; a one-line ``BakeError`` is an acceptable refusal too.
An audit hook checks that loading opens nothing outside the mutant's folder but Python's own files.

Derandomised and bounded (about 60 s on 2 cores), so CI is reproducible; the outcome counts are printed
(``pytest -s``).
"""

from __future__ import annotations

import base64
import copy
import json
import math
import os
import struct
import sys
import tempfile
from collections import Counter
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import shared_files
from gltf_factory import make_gltf
from crowd.anim.bake import MAX_ROWS, BakeError, bake
from crowd.anim.palette_reference import reference_palette
from crowd.anim.processor_inputs import INTERPOLATIONS
from crowd.asset import gltf
from crowd.asset.gltf import load_character
from crowd.asset.gltf.reader import GltfImportError
from crowd.asset.gltf_write import glb_bytes
from crowd.asset.pose import morph_vertices, sample_morph_weights
from crowd.asset.zombie import ASSET_PATH

JSON_EXAMPLES = 220
BYTE_EXAMPLES = 220
FUZZ = settings(max_examples=100, deadline=None, derandomize=True, database=None, print_blob=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much])
BAKE_FPS = 30
PHASES = np.array([0.0, 0.37, 0.81, 1.0])

# -- what the importer opens: audit hooks cannot be removed, so the hook stays installed and only
# records while this flag is set, around load_character.
_AUDIT = {"active": False, "opened": []}


def _audit(event, args):
    if _AUDIT["active"] and event == "open" and args:
        _AUDIT["opened"].append(args[0])


sys.addaudithook(_audit)
_PYTHON_DIRS = tuple({str(Path(p).resolve()) for p in (sys.prefix, sys.base_prefix, *sys.path) if p})


def _outside_opens(folder: Path) -> list:
    """Files the load opened outside `folder`: none but Python's own imports and the generated LODs' cache
    (crowd.cache, kept by a name the file's contents hash to, written atomically with the process's umask,
    which crowd.files reads from /proc)."""
    from crowd.cache import cache_dir

    inside = str(folder.resolve())
    cache = os.path.realpath(cache_dir("lods"))
    bad = []
    for p in _AUDIT["opened"]:
        if isinstance(p, int):
            continue  # an already open descriptor
        text = os.path.realpath(os.fsdecode(p))
        if text.startswith(inside + os.sep) or text.startswith(cache + os.sep) or text == os.path.realpath("/proc/self/status"):
            continue
        if text.endswith((".py", ".pyc", ".so", ".pth")) and text.startswith(_PYTHON_DIRS):
            continue  # an import during the load
        bad.append(text)
    return bad


# -- the sources, parsed once

class Source:
    """A model as (JSON document, its buffers' bytes) that a mutant is written back from."""

    def __init__(self, path: Path):
        self.path = path
        data = path.read_bytes()
        self.glb = data[:4] == b"glTF"
        if self.glb:
            n = struct.unpack_from("<I", data, 12)[0]
            self.doc = json.loads(data[20:20 + n])
            self.buffers = [data[20 + n + 8:]]
        else:
            self.doc = json.loads(data)
            self.buffers = [base64.b64decode(b["uri"].partition(",")[2]) for b in self.doc["buffers"]]

    def write(self, folder: Path, doc: dict, buffers: list[bytes]) -> Path:
        if self.glb:
            js = json.dumps(doc).encode()
            js += b" " * (-len(js) % 4)
            blob = buffers[0]
            body = struct.pack("<I4s", len(js), b"JSON") + js + struct.pack("<I4s", len(blob), b"BIN\x00") + blob
            out = folder / self.path.name
            out.write_bytes(b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body)
            return out
        if buffers is not self.buffers:  # re-encode only what changed
            doc = dict(doc, buffers=[dict(b, uri=b["uri"] if data is old else "data:application/octet-stream;base64," + base64.b64encode(data).decode())
                                     for b, data, old in zip(doc["buffers"], buffers, self.buffers)])
        out = folder / self.path.name
        out.write_text(json.dumps(doc))
        return out


# The morph targets, weights channels and default weights the samples lack: the test strip with two
# targets (tests/gltf_factory.py), written sparse by the project's writer.
_MORPH_FOLDER = tempfile.TemporaryDirectory(prefix="morph_source")
_MORPH_PATH = Path(_MORPH_FOLDER.name) / "morph.glb"
_MORPH_PATH.write_bytes(glb_bytes(load_character(make_gltf(Path(_MORPH_FOLDER.name), morph=True, interpolation="CUBICSPLINE"), scale=1.0),
                                  sparse=True))
SOURCES = [Source(p) for p in [ASSET_PATH, *shared_files(), _MORPH_PATH]]

# -- JSON-level mutations

COLLECTIONS = ("accessors", "bufferViews", "buffers", "nodes", "skins", "meshes", "animations", "materials",
               "textures", "images", "samplers")
WRONG = ["x", "", [], {}, None, True, False, [1, 2], {"a": 1}, [None], "../outside.bin", "/etc/hostname",
         "data:application/octet-stream;base64,AAAA"]
NUMBERS = [-1, -2, -(2**31), 0, 1, 2, 3, 4, 5, 7, 252, 253, 2**16, 2**31, 2**32 + 1, 2**53, 2**63, 10**30,
           0.5, -0.0, 1e-30, 1e30, -1e30, 1e308, math.nan, math.inf, -math.inf, 5126, 5123, 5121, 5125, 5120]


def _value(draw):
    """A replacement value: a fresh copy, so no mutant shares (and later changes) the pool's lists."""
    return copy.deepcopy(draw(st.sampled_from(NUMBERS + WRONG)))


def _paths(value, prefix=()):
    """Every path to a value inside a JSON element (containers included, the element itself excluded)."""
    out = []
    if isinstance(value, dict):
        for k, v in value.items():
            out.append(prefix + (k,))
            out.extend(_paths(v, prefix + (k,)))
    elif isinstance(value, list) and len(value) <= 64:  # long arrays (joint lists) get a few entries
        for i, v in enumerate(value):
            out.append(prefix + (i,))
            out.extend(_paths(v, prefix + (i,)))
    elif isinstance(value, list):
        for i in (0, 1, len(value) // 2, len(value) - 1):
            out.append(prefix + (i,))
    return out


def _parent(root, path):
    for k in path[:-1]:
        root = root[k]
    return root


@st.composite
def json_mutant(draw):
    source = draw(st.sampled_from(SOURCES))
    doc = copy.deepcopy(source.doc)
    mutations = []
    for _ in range(draw(st.integers(1, 3))):
        name = draw(st.sampled_from([c for c in COLLECTIONS if doc.get(c)]))
        seq = doc[name]
        index = draw(st.integers(0, len(seq) - 1))
        op = draw(st.sampled_from(["set", "set", "set", "nudge", "drop", "swap_elements", "swap_in_list", "shorten"]))
        if op == "swap_elements" and len(seq) > 1:
            other = draw(st.integers(0, len(seq) - 1))
            seq[index], seq[other] = seq[other], seq[index]
            mutations.append(f"swap {name}[{index}] {name}[{other}]")
            continue
        paths = _paths(seq[index]) if isinstance(seq[index], (dict, list)) else []
        if not paths:
            seq[index] = _value(draw)
            mutations.append(f"{name}[{index}] = {seq[index]!r}")
            continue
        path = draw(st.sampled_from(paths))
        holder = _parent(seq[index], path)
        key = path[-1]
        old = holder[key]
        where = f"{name}[{index}]" + "".join(f"[{k!r}]" for k in path)
        if op == "drop":
            if isinstance(holder, dict):
                del holder[key]
            else:
                holder.pop(key)
            mutations.append(f"drop {where}")
        elif op == "nudge" and isinstance(old, (int, float)) and not isinstance(old, bool):
            holder[key] = old + draw(st.sampled_from([-1, 1, 3, -4, len(seq), 2**20])) if isinstance(old, int) else old * draw(st.sampled_from([-1.0, 1e30, 1e-30, 0.0, 3.0]))
            mutations.append(f"{where}: {old!r} -> {holder[key]!r}")
        elif op == "swap_in_list" and isinstance(old, list) and len(old) > 1:
            old[0], old[-1] = old[-1], old[0]
            mutations.append(f"swap ends of {where}")
        elif op == "shorten" and isinstance(old, list) and old:
            old.pop()
            mutations.append(f"shorten {where}")
        else:
            holder[key] = _value(draw)
            mutations.append(f"{where} = {holder[key]!r}")
    return source, doc, source.buffers, None, "; ".join(mutations)


# -- byte-level mutations

@st.composite
def byte_mutant(draw):
    source = draw(st.sampled_from(SOURCES))
    buffers = list(source.buffers)
    op = draw(st.sampled_from(["flip", "flip", "zero", "garble", "cut_binary", "cut_file"]))
    if op == "cut_file":
        return source, source.doc, buffers, draw(st.floats(0.0, 1.0)), "cut the file"
    views = source.doc["bufferViews"]
    vi = draw(st.integers(0, len(views) - 1))
    view = views[vi]
    bi = view["buffer"]
    start, length = view.get("byteOffset", 0), view["byteLength"]
    data = bytearray(buffers[bi])
    if op == "cut_binary":
        at = start + draw(st.integers(0, length))
        buffers[bi] = bytes(data[:at])
        return source, source.doc, buffers, None, f"cut buffer {bi} at {at} (in bufferView {vi})"
    at = start + draw(st.integers(0, length - 1))
    if op == "flip":
        bit = draw(st.integers(0, 7))
        data[at] ^= 1 << bit
        what = f"flip bit {bit} of byte {at}"
    else:
        size = min(draw(st.integers(1, 64)), start + length - at)
        fill = bytes(size) if op == "zero" else draw(st.binary(min_size=size, max_size=size))
        data[at:at + size] = fill
        what = f"{op} {size} bytes at {at}"
    buffers[bi] = bytes(data)
    return source, source.doc, buffers, None, f"{what} (bufferView {vi} of buffer {bi})"


# -- the property

def _frames(clips) -> int:
    return sum(max(1, math.ceil(c.duration * BAKE_FPS)) + 1 for c in clips) + 2


def check_mutant(source: Source, doc, buffers, cut, mutation: str) -> str:
    """The outcome ('refused by the importer', 'refused by the bake', 'loaded'), or an AssertionError."""
    with tempfile.TemporaryDirectory(prefix="mutant") as tmp:
        outer = Path(tmp)
        (outer / "outside.bin").write_bytes(bytes(64))  # a real file out of bounds: opening it would be caught
        folder = outer / "model"
        folder.mkdir()
        path = source.write(folder, doc, buffers)
        if cut is not None:
            data = path.read_bytes()
            path.write_bytes(data[: int(len(data) * cut)])
        _AUDIT["opened"] = []
        _AUDIT["active"] = True
        try:
            character = load_character(path)
        except GltfImportError as exc:
            message = str(exc)
            assert "\n" not in message and message.startswith(path.name + ": "), (mutation, message)
            assert gltf._UNEXPECTED not in message, (mutation, message)
            return "refused by the importer"
        finally:
            _AUDIT["active"] = False
            outside = _outside_opens(folder)
            assert not outside, (mutation, outside)
        for m in character.meshes:
            assert np.all(np.isfinite(m.positions)) and np.all(np.isfinite(m.normals)), mutation
            assert np.allclose(np.linalg.norm(m.normals, axis=1), 1.0, atol=1e-3), mutation
        assert np.all(np.isfinite(character.morph_defaults)), mutation
        for clip in character.clips:  # morph weights and morphed vertices are finite wherever they are sampled
            weights = sample_morph_weights(character.morph_defaults, clip, PHASES)
            assert np.all(np.isfinite(weights)), mutation
            for m in character.meshes:
                if m.morph_count:
                    assert all(np.all(np.isfinite(v)) for w in weights for v in morph_vertices(m, w)), mutation
        for a in character.attachments:
            assert np.all(np.isfinite(a.offset)) and np.all(np.isfinite(a.mesh.positions)), mutation
        for prop in character.props.values():  # the weapons stage draws a prop through inverse(grip)
            assert np.all(np.isfinite(np.linalg.inv(prop.grip))) and np.all(np.isfinite(prop.mesh.positions)), mutation
        if _frames(character.clips) > MAX_ROWS:
            return "too long to bake"  # the bake refuses it after sampling every frame: not worth the time here
        try:
            baked = bake(character.skeleton, character.clips, BAKE_FPS)
        except BakeError as exc:
            assert "\n" not in str(exc), (mutation, str(exc))
            return "refused by the bake"
        n = len(baked.clips)
        layers = np.zeros((n * len(PHASES) + 1, 1, 4), np.float32)
        layers[:-1, 0, 0] = np.repeat(np.arange(n), len(PHASES))
        layers[:-1, 0, 1] = np.tile(PHASES, n)
        layers[:-1, 0, 2] = 1.0  # the last agent has weight 0: the processor's rest-pose fallback
        layers[:, 0, 3] = -1.0
        for interpolation in INTERPOLATIONS:
            with np.errstate(all="ignore"):
                palette = reference_palette(baked, layers, interpolation=interpolation)
            assert np.all(np.isfinite(palette)), (mutation, interpolation)
        return "loaded"


def _run(strategy, examples: int, label: str) -> Counter:
    outcomes: Counter = Counter()

    @settings(FUZZ, max_examples=examples)
    @given(strategy)
    def fuzz(mutant):
        outcomes[check_mutant(*mutant)] += 1

    fuzz()
    print(f"\n{label}: {sum(outcomes.values())} mutants of {len(SOURCES)} files: "
          + ", ".join(f"{k} {v}" for k, v in sorted(outcomes.items())))
    return outcomes


def test_json_level_mutants_are_refused_or_drawable():
    outcomes = _run(json_mutant(), JSON_EXAMPLES, "JSON-level")
    assert outcomes["refused by the importer"] and outcomes["loaded"]  # the fuzzer reaches both sides


def test_byte_level_mutants_are_refused_or_drawable():
    outcomes = _run(byte_mutant(), BYTE_EXAMPLES, "byte-level")
    assert outcomes["refused by the importer"] and outcomes["loaded"]
