"""Import stage: a skinned glTF 2.0 character (.glb or .gltf) → ``Character``.

Contract: ``load_character(path, clips=None)`` returns a validated ``Character`` whose skeleton is
sorted parents-first, or raises ``GltfImportError`` with one line that names the file and the culprit.
Whatever is read but cannot be used (textures, tangent morph deltas, other characters' skins, static meshes) is
listed in ``character.warnings``; nothing is dropped silently.

Morph targets. Each skinned primitive's ``targets`` (POSITION and NORMAL deltas; sparse or dense, float
or KHR_mesh_quantization integers) become the mesh's ``morph_positions`` / ``morph_normals``; targets are
the character's by name (``extras.targetNames``, else "<mesh>.target<k>"), so a mesh's LODs and
primitives share theirs; default weights come from the mesh, overridden by the node drawing it; a
``weights`` channel becomes a ``MorphChannel`` of its clip (LINEAR, STEP or CUBICSPLINE, as stored).

Several skins. The main skin is the one most mesh nodes draw with (ties: the lowest index). Another skin
whose joints all hang, in the joint forest of the joints of every skin drawing a mesh, in a tree that
holds a joint of the main skin (a visor over the head joints, a second hand skin over the arm) is merged
into one skeleton on the union of the joints (the main skin's first, in its order; then the others' new
ones), with one warning. A joint takes the inverse bind of the first skin that lists it; a skin that
lists it with another inverse bind draws through a duplicate joint, "name@skinK": a child of that joint
at identity rest, without channels, with that skin's inverse bind, so world @ inverse bind is exactly
what glTF means. A skin on another joint tree is another character: left out, one warning.

Space: skinned vertices stay in the mesh's bind space (glTF ignores a skinned mesh node's transform).
Non-joint nodes above and between joints are folded into the joints' local transforms, and a constant
uniform scale above the root joint (0.01 and 100 are common) is factored out of the whole skeleton by
scaling joint translations, so joint transforms come out rigid and in the file's scene units.

Why this module parses glTF itself, while the writer (gltf_write) keeps pygltflib: reading is where a
hostile file attacks. pygltflib converts types silently ("count": "6" becomes 6, so a wrong file
passes as a right one), checks no ranges, and spends about 180 µs per JSON object, so a file of
millions of objects hangs before any check could run. Reading with json and struct and checking each
property where it is used made every import 6 to 10 times faster too (the zombie: 185 to 17 ms).

Hostile files (issue 18). No input makes the importer read outside its buffers, raise anything but
``GltfImportError``, run or allocate without bound, or hand the stages a value they cannot draw:
- this module reads the container (GLB chunks) and the JSON itself, and checks every property it uses
  for its JSON type and its glTF 2.0 range where it reads it: bufferViews lie within their buffer,
  accessors (sparse parts included) within their bufferView with its byteStride, each accessor has a
  type and component type its use allows, indices are below the vertex count, joint indices that carry
  weight below the skin's joint count, key times are finite, non-negative and strictly increasing;
- sizes are bounded before anything is allocated: the file and the buffers it loads (MAX_FILE_BYTES),
  the JSON's count of values (MAX_JSON_VALUES), nodes, joints, animations, channels and primitives
  (MAX_NODES ... MAX_PRIMITIVES), one accessor as the float64 values the importer makes of it
  (MAX_ACCESSOR_BYTES), all accessor reads of one import (MAX_DECODED_BYTES), a clip's length
  (MAX_CLIP_SECONDS); every walk over the node tree is linear in the number of nodes, so a file at
  every bound at once imports in about 10 s;
- external buffers must be regular files inside the model's folder: nothing else is opened;
- alignment (byteOffset a multiple of the component size, byteStride of 4) is not enforced: it matters
  to a GPU reading the buffer in place, and here bytes are copied into fresh arrays;
- what the checks still miss meets a safety net that turns it into a one-line GltfImportError too
  (with words the hostile-file tests look for, so a miss fails CI instead of hiding).

Refuse or repair. A value is repaired only where what the file means is not in doubt and the repair
leaves a correct file unchanged; each repair is named in ``character.warnings``:
- a zero quaternion as a node's rotation (a rest pose) becomes the identity, glTF's default rotation;
- NaN, infinite or zero-length normals are recomputed from the triangles (normals are derived data);
- rotations are normalised and weights renormalised to sum 1 (silently, as every engine does: exporters
  write them in float32 or 8/16 bits); weights less than WEIGHT_NOISE below 0 count as 0; vertices
  without weight are bound to the first root joint; an index count that is not a multiple of 3 loses
  its incomplete triangle.
Everything else that cannot be drawn is refused, naming the element and its index: NaN or infinity in
positions, key times and values, node transforms, inverse binds, weights, morph deltas and weights or
colours; positions, translations and morph deltas beyond ±MAX_COORDINATE, morph weights beyond
±MAX_MORPH_WEIGHT; primitives of one mesh with different numbers of targets; scales beyond ±MAX_SCALE or multiplying beyond it along a joint
chain; a zero quaternion among rotation keys (which pose the clip means there is unknown, and a bake of
it draws NaN) or a CUBICSPLINE rotation passing through zero; negative weights; a clip longer than
MAX_CLIP_SECONDS; extensions the file requires that the importer does not implement (Draco, meshopt);
a file none of whose animations moves the skin's joints (the crowd has nothing to play).
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import json
import struct
from pathlib import Path
from typing import NoReturn
from urllib.parse import unquote

import numpy as np

from .. import transforms as tf
from .gltf_materials import Materials
from .pose import sample_clip
from .morph_transfer import transfer_targets
from .pieces import attachments_as_pieces
from .root_motion import take_out_root_motion
from .units import AUTO, to_crowd_units
from .model import MAX_MORPHS, Attachment, Channel, Character, Clip, ModelError, MorphChannel, Prop, RigidMesh, Skeleton, SkinnedMesh, vertex_normals

_COMPONENT = {5120: np.dtype("<i1"), 5121: np.dtype("<u1"), 5122: np.dtype("<i2"), 5123: np.dtype("<u2"),
              5125: np.dtype("<u4"), 5126: np.dtype("<f4")}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_FLOAT, _UNSIGNED = (5126,), (5121, 5123, 5125)
_SINGULAR = {"accessors": "accessor", "bufferViews": "bufferView", "buffers": "buffer", "nodes": "node",
             "meshes": "mesh", "skins": "skin", "animations": "animation", "materials": "material",
             "textures": "texture", "images": "image", "samplers": "sampler"}
LOOP_ANGLE_TOLERANCE = np.radians(2.0)  # first and last pose this close → the clip loops
LOOP_DISTANCE_TOLERANCE = 0.01

# Budgets: far above any character file (the built-in zombie is 0.76 MB, 10,511 JSON values; the largest
# sample, Quaternius' Matt, 1.8 MB and 30,661), far below what exhausts a small CI machine.
MAX_FILE_BYTES = 1 << 30  # the model file and every buffer it loads, together
MAX_JSON_VALUES = 4_000_000  # json.loads makes an object of each: a few hundred MB at most
MAX_NODES = 1 << 16
# Items whose reading costs more than their JSON (about 0.1-0.5 ms each): a game character has a few
# hundred animations, tens of thousands of channels and under a hundred primitives.
MAX_ANIMATIONS = 4096
MAX_CHANNELS = 1 << 18  # channel entries of all animations together
MAX_PRIMITIVES = 1 << 14  # primitives read, skinned and rigid (a rigid mesh is read once per node using it)
MAX_JOINTS = 1 << 16  # SkinnedMesh.joints is uint16
MAX_ACCESSOR_BYTES = 256 << 20  # one accessor, as the float64 values the importer makes of it
MAX_DECODED_BYTES = 1 << 30  # every accessor read of one import, together
# Values the stages can draw (float32 on the GPU, a shadow map around the crowd).
MAX_COORDINATE = 1e6  # positions and translations, in the file's units (metres)
MAX_SCALE = 1e6  # one scale component, and the product of the largest scales along a joint chain
MAX_CLIP_SECONDS = 3600.0
MAX_MORPH_WEIGHT = 10.0  # a morph weight, keyed or default: glTF allows any (overshoots, negative correctives)
ZERO_QUATERNION = 1e-6  # a rotation this short has no direction (int16-normalised keys are >= 3e-5)
WEIGHT_NOISE = 1e-6  # float exporters leave -1e-8 where they mean 0
AFFINE_TOLERANCE = 1e-4  # a matrix's last row against (0, 0, 0, 1)
MAX_LOD = 15
_SAFE_EXTENSION_PREFIXES = ("KHR_materials_", "KHR_texture_", "EXT_texture_", "KHR_lights_", "KHR_xmp")
_SAFE_EXTENSIONS = {"KHR_mesh_quantization"}  # any component type is read as numbers: that is all it asks
_UNEXPECTED = "the importer failed unexpectedly"  # the safety net's words: a test treats them as a bug


class GltfImportError(ValueError):
    """A file the importer cannot turn into a correct character. The message is one line."""


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0][:200] if text else type(exc).__name__


def _show(value) -> str:
    """A JSON value for a one-line message: short, newlines escaped."""
    try:
        text = repr(value)
    except ValueError:  # an int past Python's digit limit
        return f"a {type(value).__name__}"
    return text if len(text) <= 48 else text[:45] + "..."


def _is_whole(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _first(mask: np.ndarray) -> int:
    """Index of the first row with a True anywhere (rows are the leading axis)."""
    return int(np.argmax(mask.reshape(mask.shape[0], -1).any(axis=1)))


class _Reader:
    """The file's JSON and buffers, read with every property checked where it is used."""

    def __init__(self, path: Path):
        self.path = path
        self.where = path.name
        self.warnings: list[str] = []
        self._loaded_bytes = 0
        self._decoded_bytes = 0
        self.doc, self.blob = self._container(path)
        asset = self.doc.get("asset")
        version = asset.get("version") if isinstance(asset, dict) else None
        if not isinstance(version, str) or not version.startswith("2"):
            self.fail(f"glTF version {version!r} is not 2.x" if isinstance(version, str) else "glTF version is missing (asset.version)")
        required = self.doc.get("extensionsRequired") or []
        if not isinstance(required, list):
            self.fail("extensionsRequired must be an array")
        for ext in required:
            if not isinstance(ext, str) or not (ext in _SAFE_EXTENSIONS or ext.startswith(_SAFE_EXTENSION_PREFIXES)):
                self.fail(f"requires extension {_show(ext)}, which this importer does not implement")
        self._buffers: dict[int, bytes] = {}
        self._cache: dict[int, np.ndarray] = {}
        self._trs: dict[int, tuple] = {}
        self._local: dict[int, np.ndarray] = {}
        self._primitives = 0

    def fail(self, msg: str) -> NoReturn:
        raise GltfImportError(f"{self.where}: {msg}")

    # -- the container

    def _charge_file(self, size: int, what: str) -> None:
        """Counts `size` bytes against MAX_FILE_BYTES, or refuses them and counts nothing (an image left
        out for its size must not use up the budget of what comes after it)."""
        if self._loaded_bytes + size > MAX_FILE_BYTES:
            self.fail(f"{what} would bring the bytes read to {self._loaded_bytes + size:,}, more than the {MAX_FILE_BYTES:,} allowed")
        self._loaded_bytes += size

    def _read_file(self, target: Path, what: str) -> bytes:
        """A file's bytes, refused from its size before a byte is read. A file whose size is not what
        it says (growing meanwhile, or a /proc-like file reporting 0) is refused: it cannot pass the budget."""
        size = target.stat().st_size
        self._charge_file(size, what)
        with open(target, "rb") as f:
            data = f.read(size + 1)
        if len(data) != size:
            self.fail(f"{what} changed size while being read")
        return data

    def _container(self, path: Path) -> tuple[dict, bytes | None]:
        """(the JSON document, the GLB binary chunk or None)."""
        try:
            data = self._read_file(path, "the file")
        except OSError as exc:
            self.fail(f"cannot be read ({exc.strerror})")
        blob = None
        if data[:4] == b"glTF":
            if len(data) < 12:
                self.fail("not a readable glTF file (GLB header is cut short)")
            version, length = struct.unpack_from("<II", data, 4)
            if version != 2:
                self.fail(f"GLB container version {version} is not 2")
            if length > len(data):
                self.fail(f"not a readable glTF file (GLB header says {length} bytes, the file has {len(data)})")
            chunks, offset, view = [], 12, memoryview(data)  # views: the binary chunk is not copied
            while offset + 8 <= length:
                size, kind = struct.unpack_from("<I4s", data, offset)
                if offset + 8 + size > length:
                    self.fail(f"not a readable glTF file (GLB chunk {len(chunks)} runs past the end of the file)")
                chunks.append((kind, view[offset + 8: offset + 8 + size]))
                offset += 8 + size
            if not chunks or chunks[0][0] != b"JSON":
                self.fail("not a readable glTF file (the first GLB chunk is not JSON)")
            text_bytes = bytes(chunks[0][1]).rstrip(b" \x00")  # the spec pads with spaces; some writers with zeros
            if len(chunks) > 1 and chunks[1][0] == b"BIN\x00":
                blob = chunks[1][1]
        else:
            text_bytes = data
        try:
            text = text_bytes.decode("utf-8-sig")
        except UnicodeDecodeError:
            self.fail("not a readable glTF file (the JSON is not UTF-8)")
        # Outside strings every JSON value but a container's first follows a comma, so this bounds the
        # values json.loads will make (base64 data URIs hold no commas or brackets).
        values = text.count(",") + text.count("[") + text.count("{")
        if values > MAX_JSON_VALUES:
            self.fail(f"the JSON holds about {values:,} values, more than the {MAX_JSON_VALUES:,} allowed")
        try:
            doc = json.loads(text)
        except (ValueError, RecursionError) as exc:
            self.fail(f"not a readable glTF file ({_one_line(exc)})")
        if not isinstance(doc, dict):
            self.fail("not a readable glTF file (the JSON is not an object)")
        return doc, blob

    # -- typed access to the JSON

    def array(self, name: str) -> list:
        value = self.doc.get(name)
        if value is None:
            return []
        if not isinstance(value, list):
            self.fail(f"{name!r} must be an array, got {_show(value)}")
        return value

    def item(self, name: str, index, kind: str | None = None) -> dict:
        seq = self.array(name)
        kind = kind or _SINGULAR[name]
        if not _is_whole(index) or not 0 <= index < len(seq):
            self.fail(f"{kind} index {_show(index)} is out of range")
        obj = seq[index]
        if not isinstance(obj, dict):
            self.fail(f"{_SINGULAR[name]} {index} is not a JSON object")
        return obj

    def whole(self, obj: dict, key: str, where: str, default=None, lo: int = 0, hi: int | None = None, required=False):
        v = obj.get(key)
        if v is None:
            if required:
                self.fail(f"{where} has no {key}")
            return default
        if not _is_whole(v) or v < lo or (hi is not None and v > hi):
            bounds = f"from {lo} to {hi}" if hi is not None else f"of at least {lo}"
            self.fail(f"{where}: {key} must be a whole number {bounds}, got {_show(v)}")
        return v

    def index(self, obj: dict, key: str, name: str, where: str, required=False):
        v = obj.get(key)
        if v is None:
            if required:
                self.fail(f"{where} has no {key}")
            return None
        n = len(self.array(name))
        if not _is_whole(v) or not 0 <= v < n:
            self.fail(f"{where}: {key} {_show(v)} is out of range (the file has {n} {name})")
        return v

    def obj(self, obj: dict, key: str, where: str) -> dict | None:
        v = obj.get(key)
        if v is not None and not isinstance(v, dict):
            self.fail(f"{where}: {key} must be a JSON object, got {_show(v)}")
        return v

    def list(self, obj: dict, key: str, where: str) -> list:
        v = obj.get(key)
        if v is None:
            return []
        if not isinstance(v, list):
            self.fail(f"{where}: {key} must be an array, got {_show(v)}")
        return v

    def choice(self, obj: dict, key: str, where: str, choices, default=None):
        v = obj.get(key, default)
        if v not in choices or not isinstance(v, str):
            self.fail(f"{where}: {key} must be one of {', '.join(choices)}, got {_show(v)}")
        return v

    def numbers(self, obj: dict, key: str, n: int, where: str, default) -> np.ndarray:
        v = obj.get(key)
        if v is None:
            return np.array(default, dtype=np.float64)
        if not isinstance(v, list) or len(v) != n or not all(_is_number(x) for x in v):
            self.fail(f"{where}: {key} must be {n} numbers, got {_show(v)}")
        try:
            a = np.array(v, dtype=np.float64)
        except OverflowError:
            a = np.array([np.inf])
        if not np.all(np.isfinite(a)):
            self.fail(f"{where}: {key} holds NaN or infinity")
        return a

    # -- buffers, bufferViews, accessors

    def buffer(self, index: int) -> tuple[bytes, int]:
        """(the buffer's bytes, its byteLength)."""
        buf = self.item("buffers", index)
        where = f"buffer {index}"
        byte_length = self.whole(buf, "byteLength", where, lo=1, required=True)
        if index in self._buffers:
            return self._buffers[index], byte_length
        uri = buf.get("uri")
        if uri is None:
            if self.blob is None:
                self.fail(f"{where} has no uri and the file has no binary chunk")
            if index != 0:
                self.fail(f"{where} has no uri: only buffer 0 may refer to the GLB binary chunk")
            data = self.blob
        elif not isinstance(uri, str):
            self.fail(f"{where}: uri must be a string, got {_show(uri)}")
        else:
            data = self.uri_bytes(uri, where, " (glTF buffers are base64)")
        if len(data) < byte_length:
            self.fail(f"{where} holds {len(data)} bytes, byteLength says {byte_length}")
        self._buffers[index] = data
        return data, byte_length

    def uri_bytes(self, uri: str, where: str, base64_note: str = "") -> bytes:
        """The bytes a buffer's or an image's uri names: a base64 data URI (counted against the file
        budget), or a regular file inside the model's folder."""
        if not uri.startswith("data:"):
            return self._external(uri, where)
        head, comma, payload = uri.partition(",")
        if not comma or not head.endswith(";base64"):
            self.fail(f"{where} has a malformed data URI{base64_note}")
        self._charge_file(len(payload) * 3 // 4, f"{where}'s data URI")
        try:
            return base64.b64decode(payload, validate=False)
        except (binascii.Error, ValueError):
            self.fail(f"{where} has a malformed data URI")

    def _external(self, uri: str, where: str) -> bytes:
        folder = self.path.parent.resolve()
        try:
            target = (folder / unquote(uri)).resolve()
        except (OSError, ValueError, RuntimeError):  # NUL bytes, symlink loops
            self.fail(f"{where} uri {_show(uri)} is not a usable path")
        if folder != target and folder not in target.parents:
            self.fail(f"{where} uri {_show(uri)} points outside the file's folder")
        try:
            if not target.exists():
                self.fail(f"{where} file {_show(uri)} is missing from the model's folder")
            if not target.is_file():  # a FIFO or a device would block or never end
                self.fail(f"{where} file {_show(uri)} is not a regular file in the model's folder")
            return self._read_file(target, f"{where} file {_show(uri)}")
        except OSError as exc:
            self.fail(f"{where} file {_show(uri)} cannot be read ({exc.strerror})")

    def view(self, index: int) -> tuple[bytes, int, int, int | None]:
        """(buffer bytes, the view's first byte, its byteLength, its byteStride or None)."""
        v = self.item("bufferViews", index)
        where = f"bufferView {index}"
        buffer = self.index(v, "buffer", "buffers", where, required=True)
        start = self.whole(v, "byteOffset", where, default=0)
        length = self.whole(v, "byteLength", where, lo=1, required=True)
        stride = v.get("byteStride")
        stride = 0 if stride is None else stride  # 0: tightly packed (glTF 1.0 files wrote it)
        if not _is_whole(stride) or not (stride == 0 or 4 <= stride <= 252):
            self.fail(f"{where}: byteStride must be a whole number from 4 to 252, got {_show(stride)}")
        data, buffer_length = self.buffer(buffer)
        if start + length > buffer_length:
            self.fail(f"{where} runs past the end of buffer {buffer}")
        return data, start, length, stride or None

    def _view_array(self, view_index: int, offset: int, count: int, dtype: np.dtype, ncomp: int, what: str) -> np.ndarray:
        data, start, length, stride = self.view(view_index)
        item = dtype.itemsize * ncomp
        stride = stride or item
        if stride < item:
            self.fail(f"{what}: byteStride {stride} is smaller than an element ({item} bytes)")
        need = offset + stride * (count - 1) + item
        if need > length:
            self.fail(f"{what} reads {need} bytes from bufferView {view_index} of {length}")
        # Every number above is a checked non-negative int and the last row ends inside the view, which
        # lies inside the buffer: the strided walk cannot leave memory the reader owns.
        raw = np.frombuffer(data, dtype=np.uint8, count=length, offset=start)
        rows = np.lib.stride_tricks.as_strided(raw[offset:], shape=(count, item), strides=(stride, 1), writeable=False)
        return np.ascontiguousarray(rows).view(dtype).reshape(count, ncomp)

    def _charge_decoded(self, elements: int, what: str) -> None:
        size = elements * 8  # float64, what the importer turns every accessor into
        if size > MAX_ACCESSOR_BYTES:
            self.fail(f"{what} holds {elements:,} numbers ({size:,} bytes as float64), more than the {MAX_ACCESSOR_BYTES:,} allowed")
        self._decoded_bytes += size
        if self._decoded_bytes > MAX_DECODED_BYTES:
            self.fail(f"{what} brings the data read to {self._decoded_bytes:,} bytes, more than the {MAX_DECODED_BYTES:,} allowed")

    def charge_bytes(self, size: int, what: str) -> None:
        """Counts `size` bytes the import makes from the file against MAX_DECODED_BYTES."""
        self._decoded_bytes += size
        if self._decoded_bytes > MAX_DECODED_BYTES:
            self.fail(f"{what} brings the data read to {self._decoded_bytes:,} bytes, more than the {MAX_DECODED_BYTES:,} allowed")

    def accessor(self, index, use: str, types: tuple[str, ...], components: tuple[int, ...] | None = None) -> np.ndarray:
        """Accessor data as a read-only (count, ncomp) array; normalised integers become float64 per the spec.
        `types` and `components` are what this use allows; `use` names it in messages."""
        acc = self.item("accessors", index)
        what = f"accessor {index} ({use})"
        ctype = acc.get("componentType")
        if not _is_whole(ctype) or ctype not in _COMPONENT:
            self.fail(f"{what} has unknown componentType {_show(ctype)}")
        kind = acc.get("type")
        if not isinstance(kind, str) or kind not in _NCOMP:
            self.fail(f"{what} has unknown type {_show(kind)}")
        if kind not in types:
            self.fail(f"{what} must be {' or '.join(types)}, got {kind}")
        if components is not None and ctype not in components:
            names = {5120: "BYTE", 5121: "UNSIGNED_BYTE", 5122: "SHORT", 5123: "UNSIGNED_SHORT", 5125: "UNSIGNED_INT", 5126: "FLOAT"}
            self.fail(f"{what} must have componentType {' or '.join(names[c] for c in components)}, got {names[ctype]}")
        count = self.whole(acc, "count", what, lo=1, required=True)
        dtype, ncomp = _COMPONENT[ctype], _NCOMP[kind]
        if kind in ("MAT2", "MAT3") and dtype.itemsize < 4:  # no use asks for one today
            self.fail(f"{what}: {kind} of {dtype.itemsize}-byte components pads its columns, which this importer does not read")
        self._charge_decoded(count * ncomp, what)
        if index in self._cache:
            return self._cache[index]
        normalized = acc.get("normalized", False)
        if not isinstance(normalized, bool):
            self.fail(f"{what}: normalized must be true or false, got {_show(normalized)}")
        if normalized and ctype in (5125, 5126):
            self.fail(f"{what} is {'float' if ctype == 5126 else 'unsigned int'} and normalized, which glTF forbids")
        view = self.index(acc, "bufferView", "bufferViews", what)
        if view is None:
            arr = np.zeros((count, ncomp), dtype=dtype)  # glTF: an accessor without a bufferView is zeros
        else:
            arr = self._view_array(view, self.whole(acc, "byteOffset", what, default=0), count, dtype, ncomp, what)
        sparse = self.obj(acc, "sparse", what)
        if sparse is not None:
            arr = self._sparse(arr, sparse, dtype, ncomp, what)
        if normalized:
            info = np.iinfo(dtype)
            arr = np.maximum(arr.astype(np.float64) / info.max, -1.0)
        arr.flags.writeable = False  # shared through the cache: users copy (astype) before changing
        self._cache[index] = arr
        return arr

    def _sparse(self, arr: np.ndarray, sparse: dict, dtype: np.dtype, ncomp: int, what: str) -> np.ndarray:
        where = f"{what} sparse"
        count = self.whole(sparse, "count", where, lo=1, hi=arr.shape[0], required=True)
        indices = self.obj(sparse, "indices", where) or self.fail(f"{where} has no indices")
        values = self.obj(sparse, "values", where) or self.fail(f"{where} has no values")
        idx_type = indices.get("componentType")
        if idx_type not in _UNSIGNED or not _is_whole(idx_type):
            self.fail(f"{where} indices have componentType {_show(idx_type)}; glTF allows 5121, 5123, 5125")
        self._charge_decoded(count * (1 + ncomp), where)
        idx = self._view_array(self.index(indices, "bufferView", "bufferViews", f"{where} indices", required=True),
                               self.whole(indices, "byteOffset", f"{where} indices", default=0), count, _COMPONENT[idx_type], 1, where)[:, 0]
        idx = idx.astype(np.int64)
        if np.any(idx >= arr.shape[0]):
            self.fail(f"{where}: index {int(idx[np.argmax(idx >= arr.shape[0])])} points past the accessor's {arr.shape[0]} elements")
        if count > 1 and np.any(np.diff(idx) <= 0):
            self.fail(f"{where}: indices must increase strictly (glTF)")
        vals = self._view_array(self.index(values, "bufferView", "bufferViews", f"{where} values", required=True),
                                self.whole(values, "byteOffset", f"{where} values", default=0), count, dtype, ncomp, where)
        arr = arr.copy()
        arr[idx] = vals
        return arr

    def count_primitive(self, label: str) -> None:
        self._primitives += 1
        if self._primitives > MAX_PRIMITIVES:
            self.fail(f"{label}: more than the {MAX_PRIMITIVES:,} primitives allowed")

    # -- nodes

    def node_where(self, i: int) -> str:
        name = self.item("nodes", i).get("name")
        return f"node {i} ({name!r})" if isinstance(name, str) and name else f"node {i}"

    def trs(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """(t, q, s, shear) of node i, checked: a `matrix` node is decomposed, shear says how far TRS is from it."""
        if i in self._trs:
            return self._trs[i]
        node = self.item("nodes", i)
        where = self.node_where(i)
        matrix = node.get("matrix")
        if matrix is not None and matrix != []:
            m = self.numbers(node, "matrix", 16, where, None).reshape(4, 4).T  # glTF matrices are column-major
            if np.max(np.abs(m)) > max(MAX_COORDINATE, MAX_SCALE):
                self.fail(f"{where}: matrix holds {float(np.max(np.abs(m))):.3g}, beyond ±{max(MAX_COORDINATE, MAX_SCALE):g}")
            if np.max(np.abs(m[3] - [0.0, 0.0, 0.0, 1.0])) > AFFINE_TOLERANCE:
                self.fail(f"{where}: matrix is not affine (its last row is {m[3].tolist()})")
            t, q, s, shear = tf.mat4_decompose(m)
            self._local[i] = m
            result = (t, q, s, float(shear))
        else:
            t = self.numbers(node, "translation", 3, where, [0.0, 0.0, 0.0])
            if np.max(np.abs(t)) > MAX_COORDINATE:
                self.fail(f"{where}: translation {t.tolist()} lies beyond ±{MAX_COORDINATE:g}")
            q = self.numbers(node, "rotation", 4, where, [0.0, 0.0, 0.0, 1.0])
            if np.linalg.norm(q) < ZERO_QUATERNION:
                self.warnings.append(f"{where}: rotation is the zero quaternion; used the identity")
                q = np.array([0.0, 0.0, 0.0, 1.0])
            s = self.numbers(node, "scale", 3, where, [1.0, 1.0, 1.0])
            if np.max(np.abs(s)) > MAX_SCALE:
                self.fail(f"{where}: scale {s.tolist()} lies beyond ±{MAX_SCALE:g}")
            q = tf.quat_normalize(q)
            self._local[i] = tf.trs_to_mat4(t, q, s)
            result = (t, q, s, 0.0)
        self._trs[i] = result
        return result

    def local(self, i: int) -> np.ndarray:
        """Node i's local transform as a float64 4x4 (its matrix, or its TRS with glTF's defaults)."""
        if i not in self._local:
            self.trs(i)
        return self._local[i]


def _trs_fields(node):
    t = np.array(node.translation if node.translation is not None else [0, 0, 0], dtype=np.float64)
    q = np.array(node.rotation if node.rotation is not None else [0, 0, 0, 1], dtype=np.float64)
    s = np.array(node.scale if node.scale is not None else [1, 1, 1], dtype=np.float64)
    return t, tf.quat_normalize(q), s


def node_local_matrix(node) -> np.ndarray:
    """A pygltflib node's local transform as a float64 4x4 (its matrix, or its TRS with glTF's defaults).
    For files this project wrote or already imported (bench/peers_panda.py); the importer checks its own."""
    if node.matrix is not None and len(node.matrix) == 16:
        return np.array(node.matrix, dtype=np.float64).reshape(4, 4).T  # glTF matrices are column-major
    return tf.trs_to_mat4(*_trs_fields(node))


def crowd_extras(obj) -> dict:
    """A node's or mesh's ``extras.crowd`` (piece, lod, group, socket, prop), or {} when it has none.
    `obj` is a JSON object (dict) or a pygltflib object."""
    extras = obj.get("extras") if isinstance(obj, dict) else getattr(obj, "extras", None)
    if isinstance(extras, dict) and isinstance(extras.get("crowd"), dict):
        return extras["crowd"]
    return {}


def _is_uniform(s: np.ndarray, tol: float = 1e-5) -> bool:
    return float(np.max(np.abs(s - s[0]))) <= tol * max(1.0, abs(float(s[0])))


class _Fold:
    """A constant similarity P (rigid Q and uniform scale sp) applied on the left of a joint's local TRS."""

    def __init__(self, matrix: np.ndarray):
        t, q, s, shear = tf.mat4_decompose(matrix)
        self.ok = _is_uniform(s) and shear < 1e-5 and s[0] > 0
        self.t, self.q, self.s = t, q, float(s[0])
        self.identity = np.allclose(matrix, np.eye(4), atol=1e-12)

    def translation(self, t, tangent=False):
        out = self.s * tf.quat_rotate(self.q, t)
        return out if tangent else out + self.t

    def rotation(self, q):
        return tf.quat_mul(self.q, q)  # linear in q, so it also maps CUBICSPLINE tangents

    def scale(self, s):
        return self.s * np.asarray(s)


def _apply_channel(values: np.ndarray, interpolation: str, fn) -> np.ndarray:
    if interpolation != "CUBICSPLINE":
        return fn(values, False)
    out = values.copy()
    out[:, 1] = fn(values[:, 1], False)
    out[:, 0] = fn(values[:, 0], True)
    out[:, 2] = fn(values[:, 2], True)
    return out


# The built-in characters, generated by code and shipped as .glb files: a model named so is one of them.
BUILT_IN = ("zombie", "brute", "survivor")


def is_built_in(model) -> bool:
    """Whether a model name is a built-in character's (None is the zombie)."""
    return model is None or (isinstance(model, str) and model in BUILT_IN)


def load_character(path: str | Path | None = None, clips: list[str] | None = None, scale: float | str = AUTO) -> Character:
    """Import a skinned character. ``path=None`` loads the built-in zombie, a built-in's name (BUILT_IN) that
    character; ``clips`` keeps only those clips; ``scale`` is a size factor, or "auto" for a person's
    height where the file is far from it (units.py)."""
    if is_built_in(path):
        import importlib

        name = path or "zombie"
        generator = importlib.import_module(f"{__package__}.{name}")
        path = generator.ASSET_PATH
        if not path.exists():  # a copy that lost the shipped file (wheels carry it): the generator is the source of truth
            return to_crowd_units(_select_clips(generator.build_character(), clips, f"built-in {name}"), scale)
    path = Path(path)
    if not path.is_file():
        raise GltfImportError(f"{path}: no such file")
    try:
        # Hostile values are checked explicitly after each conversion; numpy's warnings on the way
        # (a signalling NaN cast to float64, a float32 overflow) are noise.
        with np.errstate(invalid="ignore", over="ignore"):
            character = _import(_Reader(path))
    except ModelError as exc:
        raise GltfImportError(f"{path.name}: {exc}") from None
    except GltfImportError:
        raise
    except (ArithmeticError, LookupError, TypeError, ValueError, AttributeError, MemoryError, RecursionError) as exc:
        # A safety net for what the checks above missed: one line for the person, and words the
        # hostile-file tests look for, so a miss still fails CI.
        raise GltfImportError(f"{path.name}: {_UNEXPECTED} ({type(exc).__name__}: {_one_line(exc)})") from None
    return to_crowd_units(transfer_targets(take_out_root_motion(attachments_as_pieces(_select_clips(character, clips, path.name)))), scale)


def _select_clips(character: Character, clips, where: str) -> Character:
    if clips is None:
        return character
    names = [c.name for c in character.clips]
    missing = [c for c in clips if c not in names]
    if missing:
        raise GltfImportError(f"{where}: no clip named {', '.join(map(repr, missing))}; clips are {', '.join(names)}")
    character.clips = [character.clip(c) for c in clips]
    return character


class _Tree:
    """The node hierarchy: parents, the joints, and each node's nearest joint above, all in linear time."""

    def __init__(self, r: _Reader):
        self.r = r
        nodes = r.array("nodes")
        if len(nodes) > MAX_NODES:
            r.fail(f"{len(nodes):,} nodes, more than the {MAX_NODES:,} allowed")
        self.nodes = [r.item("nodes", i) for i in range(len(nodes))]
        parent: dict[int, int] = {}
        for i, n in enumerate(self.nodes):
            for c in r.list(n, "children", r.node_where(i)):
                if not _is_whole(c) or not 0 <= c < len(nodes):
                    r.fail(f"node {i} has child {_show(c)} out of range")
                if c in parent:
                    r.fail(f"node {c} has two parents")
                parent[c] = i
        self.parent = parent
        done: set[int] = set()  # nodes whose chain up is known to end at a root
        for i in range(len(nodes)):
            path, on_path, k = [], set(), i
            while k is not None and k not in done:
                if k in on_path:
                    r.fail(f"node hierarchy has a cycle through node {i}")
                on_path.add(k)
                path.append(k)
                k = parent.get(k)
            done.update(path)
        self.joints: set[int] = set()
        self._above: dict[int, int | None] = {}
        self._run: dict[int, np.ndarray] = {}

    def joint_above(self, node: int) -> int | None:
        """The nearest joint strictly above `node`, or None."""
        return _nearest_joint_above(self.parent, self.joints, self._above, node)

    def run_matrix(self, node: int) -> np.ndarray:
        """For a non-joint node: the product of the locals from the top of its run of non-joint nodes
        (just below a joint, or a root) down to it, itself included; memoised, so linear in all."""
        chain, k = [], node
        while k not in self._run:
            chain.append(k)
            p = self.parent.get(k)
            if p is None or p in self.joints:
                base = None
                break
            k = p
        else:
            base = self._run[k]
        for k in reversed(chain):
            base = self.r.local(k) if base is None else base @ self.r.local(k)
            self._run[k] = base
        return self._run[node]

    def between(self, node: int) -> np.ndarray | None:
        """Product of the locals strictly between `node` and its nearest joint above (or the root);
        None when there is none."""
        p = self.parent.get(node)
        return None if p is None or p in self.joints else self.run_matrix(p)


def _import(r: _Reader) -> Character:
    tree = _Tree(r)
    nodes = tree.nodes
    warn = r.warnings

    skins = r.array("skins")
    if not skins:
        r.fail("no skin: this importer needs a skinned character")
    skin_use: dict[int, int] = {}
    for i, n in enumerate(nodes):
        where = r.node_where(i)
        mesh, skin = r.index(n, "mesh", "meshes", where), r.index(n, "skin", "skins", where)
        if mesh is not None and skin is not None:
            skin_use[skin] = skin_use.get(skin, 0) + 1
    if not skin_use:
        r.fail("no node draws a mesh with a skin")
    skin_index = max(skin_use, key=lambda k: (skin_use[k], -k))
    # Every skin that draws a mesh is checked; those that hang in the main skin's joint trees are merged.
    skin_joints = {skin_index: _skin_joints(r, skin_index)}
    for k in sorted(skin_use):
        if k != skin_index:
            skin_joints[k] = _skin_joints(r, k)
    merged = _mergeable_skins(r, tree, skin_index, skin_joints, warn)
    # The union: the main skin's joints in its order, then the other skins' new joints in skin order.
    src_joints = list(skin_joints[skin_index])
    listed = set(src_joints)
    for k in merged[1:]:
        for j in skin_joints[k]:
            if j not in listed:
                listed.add(j)
                src_joints.append(j)
    if len(src_joints) > MAX_JOINTS:
        r.fail(f"skins {', '.join(map(str, merged))} have {len(src_joints):,} joints together, more than the {MAX_JOINTS:,} a vertex can address")
    tree.joints = listed
    joint_parent = tree.joint_above

    # Parents-first order, stable in the union's order.
    position = {j: i for i, j in enumerate(src_joints)}
    depth: dict[int, int] = {}
    for j in src_joints:
        chain, k = [], j
        while k is not None and k not in depth:
            chain.append(k)
            k = joint_parent(k)
        d = -1 if k is None else depth[k]
        for k in reversed(chain):
            d += 1
            depth[k] = d
    order = sorted(src_joints, key=lambda j: (depth[j], position[j]))
    new_index = {node: i for i, node in enumerate(order)}
    jc = len(order)
    names, seen = [], set()
    for i, node in enumerate(order):
        name = nodes[node].get("name")
        name = name if isinstance(name, str) and name else f"joint{i}"
        while name in seen:  # the first repeat gets ".i"; a name that still clashes gets it again
            name = f"{name}.{i}"
        seen.add(name)
        names.append(name)
    parent_list = [new_index[joint_parent(n)] if joint_parent(n) is not None else -1 for n in order]

    rest_t = np.zeros((jc, 3))
    rest_q = np.zeros((jc, 4))
    rest_s = np.zeros((jc, 3))
    folds: list[_Fold | None] = []
    for i, node in enumerate(order):
        t, q, s, shear = r.trs(node)
        if shear > 1e-5:
            warn.append(f"joint {names[i]!r} matrix has shear {shear:.2g}; approximated by TRS")
        above = tree.between(node)
        fold = None if above is None else _Fold(above)
        if fold is None or fold.identity:
            folds.append(None)
        else:
            if not fold.ok:
                r.fail(f"non-uniform scale or shear on a non-joint node above joint {names[i]!r} is not supported")
            t, q, s = fold.translation(t), fold.rotation(q), fold.scale(s)
            folds.append(fold)
        rest_t[i], rest_q[i], rest_s[i] = t, q, s

    # Inverse binds: each joint takes the first merged skin's (the main skin's first) that lists it. A
    # skin that lists a joint with another inverse bind draws through a duplicate joint: a child of that
    # joint at identity rest, so its world transform is the joint's and world @ ibm is what glTF means.
    ibm_file = np.empty((jc, 4, 4))
    assigned = np.zeros(jc, dtype=bool)
    skin_maps: dict[int, np.ndarray] = {}
    dup_of: list[int] = []
    dup_ibm: list[np.ndarray] = []
    for k in merged:
        ibm_k = _skin_inverse_binds(r, k, len(skin_joints[k]))
        idx = np.array([new_index[j] for j in skin_joints[k]], dtype=np.int64)
        fresh = ~assigned[idx]
        ibm_file[idx[fresh]] = ibm_k[fresh]
        assigned[idx[fresh]] = True
        held = ibm_file[idx]
        size = np.maximum(1.0, np.maximum(np.abs(held).max(axis=(1, 2)), np.abs(ibm_k).max(axis=(1, 2))))
        differ = np.flatnonzero(np.abs(held - ibm_k).max(axis=(1, 2)) > 1e-6 * size)
        if jc + len(dup_of) + len(differ) > MAX_JOINTS:
            r.fail(f"skins {', '.join(map(str, merged))} need more than the {MAX_JOINTS:,} joints a vertex can address "
                   "(duplicates for differing inverse binds included)")
        mapping = idx.copy()
        for p in differ:
            o = int(idx[p])
            mapping[p] = jc + len(dup_of)
            name = f"{names[o]}@skin{k}"
            while name in seen:
                name = f"{name}.{mapping[p]}"
            seen.add(name)
            names.append(name)
            dup_of.append(o)
            dup_ibm.append(ibm_k[p])
        skin_maps[k] = mapping
    if len(merged) > 1:
        warn.append(f"merged skins {', '.join(map(str, merged))} into one skeleton ({jc + len(dup_of)} joints; "
                    f"{len(dup_of)} duplicated for differing inverse binds)")
    if dup_of:
        n = len(dup_of)
        parent_list += dup_of
        rest_t = np.concatenate([rest_t, np.zeros((n, 3))])
        rest_q = np.concatenate([rest_q, np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))])
        rest_s = np.concatenate([rest_s, np.ones((n, 3))])
        folds += [None] * n
        ibm_file = np.concatenate([ibm_file, np.array(dup_ibm)])
        jc += n
    parents = np.array(parent_list, dtype=np.int32)

    # Factor a constant uniform scale above the root joint(s) out of the skeleton: child translations
    # are multiplied by it and the inverse binds absorb it, so joint transforms stay rigid.
    roots = [i for i in range(jc) if parents[i] < 0]
    root_scales = {round(folds[i].s, 9) if folds[i] else 1.0 for i in roots}
    factor = root_scales.pop() if len(root_scales) == 1 else 1.0
    if factor != 1.0:
        for i in roots:
            rest_s[i] /= factor
        for i in range(jc):
            if parents[i] >= 0:
                rest_t[i] *= factor

    ibm = np.diag([factor, factor, factor, 1.0]) @ ibm_file
    if not np.all(np.isfinite(ibm)):
        r.fail("inverseBindMatrices hold NaN or Inf")

    skeleton = Skeleton(tuple(names), parents, rest_t, tf.quat_normalize(rest_q), rest_s, ibm).validate()

    materials = Materials(r)
    morphs = _Morphs(r, warn)
    meshes = _read_meshes(r, tree, skin_maps, materials, morphs, warn)
    if not meshes:
        r.fail("the skinned meshes have no triangles")
    attachments, props = _read_rigid(r, tree, new_index, factor, materials, warn)
    warn.extend(materials.warnings())
    sockets = {}
    for node, i in new_index.items():
        name = crowd_extras(nodes[node]).get("socket")
        if isinstance(name, str):
            sockets[name] = i
    clips = _read_clips(r, tree, skeleton, new_index, folds, factor, morphs, warn)
    if not clips:
        r.fail("no animation animates the skin's joints: the crowd needs at least one clip")
    _check_scale_chains(r, skeleton, clips)
    name = Path(r.path).stem
    character = Character(name, skeleton, meshes, clips, attachments, props, sockets, warn, materials.textures,
                          tuple(morphs.names), np.array(morphs.defaults, np.float64))
    return character.validate()


def _skin_label(r: _Reader, k: int, joints: int) -> str:
    """'skin 1 ('Bob', 20 joints)' for messages."""
    name = r.item("skins", k).get("name")
    return f"skin {k} ({name!r}, {joints} joints)" if isinstance(name, str) and name else f"skin {k} ({joints} joints)"


def _skin_joints(r: _Reader, k: int) -> list[int]:
    """Skin k's joint nodes, checked: some, at most MAX_JOINTS, each a node, none twice."""
    skin = r.item("skins", k)
    joints = r.list(skin, "joints", f"skin {k}")
    if not joints:
        r.fail(f"skin {k} has no joints")
    if len(joints) > MAX_JOINTS:
        r.fail(f"skin {k} has {len(joints):,} joints, more than the {MAX_JOINTS:,} a vertex can address")
    for j in joints:
        r.item("nodes", j, "joint node")
    if len(set(joints)) != len(joints):
        r.fail(f"skin {k} lists a joint twice")
    return joints


def _memoised_walk(node: int, memo: dict, step) -> object:
    """Where a chain of steps from `node` ends, remembered for every node on the way, so that walks
    over a whole tree stay linear. `step(k)` is (the next node, None) to go on, or (None, the end)."""
    chain, k = [], node
    while k not in memo:
        chain.append(k)
        nxt, end = step(k)
        if nxt is None:
            break
        k = nxt
    else:
        end = memo[k]
    for k in chain:
        memo[k] = end
    return end


def _nearest_joint_above(parent: dict[int, int], joints: set[int], memo: dict, node: int) -> int | None:
    """The nearest node of `joints` strictly above `node` (None: it has none), memoised in `memo`."""
    def step(k):
        p = parent.get(k)
        return (None, p) if p is None or p in joints else (p, None)

    return _memoised_walk(node, memo, step)


def _joint_tops(tree: _Tree, joints: set[int]) -> dict[int, int]:
    """For each joint: the top joint of its tree in the forest of `joints` (parent = the nearest joint
    above). Linear in the nodes walked; tree.joints and its memo are left alone."""
    above: dict[int, int | None] = {}
    top: dict[int, int] = {}

    def step(k):
        a = _nearest_joint_above(tree.parent, joints, above, k)
        return (None, k) if a is None else (a, None)

    for j in joints:
        _memoised_walk(j, top, step)
    return top


def _mergeable_skins(r: _Reader, tree: _Tree, main: int, skin_joints: dict[int, list[int]], warn: list[str]) -> list[int]:
    """The skins that form one skeleton with the main skin, main first: those all of whose joints lie,
    in the joint forest of the joints of every skin drawing a mesh, in a tree that holds a joint of the
    main skin. The others are other characters (or do not fit one skeleton): left out, one warning each."""
    others = sorted(k for k in skin_joints if k != main)
    if not others:
        return [main]
    top = _joint_tops(tree, set().union(*skin_joints.values()))
    main_tops = {top[j] for j in skin_joints[main]}
    merged = [main]
    for k in others:
        joints = skin_joints[k]
        outside = sum(top[j] not in main_tops for j in joints)
        if not outside:
            merged.append(k)
        elif outside == len(joints):
            warn.append(f"{_skin_label(r, k, len(joints))} shares no joint tree with skin {main}: it is another character; left out")
        else:
            warn.append(f"{_skin_label(r, k, len(joints))} has {outside} joints outside skin {main}'s joint trees: "
                        "it does not fit one skeleton with it; left out")
    return merged


def _skin_inverse_binds(r: _Reader, k: int, joint_count: int) -> np.ndarray:
    """Skin k's inverse bind matrices as float64 (joint_count, 4, 4), row-major, checked (identity without them)."""
    skin = r.item("skins", k)
    ibm_index = r.index(skin, "inverseBindMatrices", "accessors", f"skin {k}")
    if ibm_index is None:
        return np.tile(np.eye(4), (joint_count, 1, 1))
    raw = r.accessor(ibm_index, "inverseBindMatrices", ("MAT4",), _FLOAT)
    if raw.shape[0] < joint_count:
        r.fail(f"skin {k}: inverseBindMatrices has {raw.shape[0]} matrices for {joint_count} joints")
    ibm = raw[:joint_count].astype(np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)
    _check_matrices(r, ibm, f"accessor {ibm_index} (inverseBindMatrices)")
    return ibm


def _check_matrices(r: _Reader, m: np.ndarray, what: str) -> None:
    """(N, 4, 4) row-major matrices: finite, bounded, affine, invertible."""
    def name(mask):
        return "the matrix" if m.shape[0] == 1 else f"matrix {_first(mask)}"

    bad = ~np.isfinite(m)
    if np.any(bad):
        r.fail(f"{what}: {name(bad)} holds NaN or infinity")
    big = np.abs(m) > max(MAX_COORDINATE, MAX_SCALE)
    if np.any(big):
        r.fail(f"{what}: {name(big)} holds a value beyond ±{max(MAX_COORDINATE, MAX_SCALE):g}")
    skew = np.abs(m[:, 3] - [0.0, 0.0, 0.0, 1.0]) > AFFINE_TOLERANCE
    if np.any(skew):
        r.fail(f"{what}: {name(skew)} is not affine (its last row is {m[_first(skew), 3].tolist()})")
    singular = np.abs(np.linalg.det(m[:, :3, :3])) < 1e-18
    if np.any(singular):
        r.fail(f"{what}: {name(singular)} is singular")


def _attr(r: _Reader, prim: dict, key: str, label: str):
    attributes = r.obj(prim, "attributes", label) or {}
    return r.index(attributes, key, "accessors", f"{label} attribute")


def _vertex_data(r: _Reader, prim: dict, key: str, label: str, v: int, types, components=None) -> np.ndarray | None:
    """An attribute with one row per vertex, or None when the primitive has none."""
    index = _attr(r, prim, key, label)
    if index is None:
        return None
    data = r.accessor(index, f"{label} {key}", types, components)
    if data.shape[0] != v:
        r.fail(f"accessor {index} ({label} {key}) has {data.shape[0]} elements for {v} vertices")
    return data


def _refuse_bad_values(r: _Reader, a: np.ndarray, what: str, item: str, limit: float | None = None,
                       beyond: str = "lies beyond ±{limit:g}") -> None:
    """Refuse, naming the first row (`item` i), a NaN or infinite value, or one beyond ±`limit` (then
    `beyond` says how, given the value and the limit)."""
    bad = ~np.isfinite(a)
    if np.any(bad):
        r.fail(f"{what}: {item} {_first(bad)} is NaN or infinite")
    if limit is not None:
        far = np.abs(a) > limit
        if np.any(far):
            r.fail(f"{what}: {item} {_first(far)} " + beyond.format(value=float(a[far][0]), limit=limit))


def _positions(r: _Reader, prim: dict, label: str) -> np.ndarray:
    index = _attr(r, prim, "POSITION", label)
    acc = r.item("accessors", index)
    if acc.get("bufferView") is None and acc.get("sparse") is None:
        r.fail(f"accessor {index} ({label} POSITION) has no data (no bufferView: compressed by an extension?)")
    what = f"accessor {index} ({label} POSITION)"
    pos = r.accessor(index, f"{label} POSITION", ("VEC3",)).astype(np.float64)
    _refuse_bad_values(r, pos, what, "vertex", MAX_COORDINATE)
    return pos


def _indices(r: _Reader, prim: dict, vertex_count: int, label: str, warn: list[str]) -> np.ndarray:
    index = r.index(prim, "indices", "accessors", label)
    if index is not None:
        idx = r.accessor(index, f"{label} indices", ("SCALAR",), _UNSIGNED)[:, 0].astype(np.int64)
    else:
        idx = np.arange(vertex_count, dtype=np.int64)
    if idx.shape[0] % 3:
        warn.append(f"{label}: {idx.shape[0]} indices are not whole triangles; the last {idx.shape[0] % 3} left out")
    idx = idx[: idx.shape[0] // 3 * 3]
    if idx.size and idx.max() >= vertex_count:
        k = int(np.argmax(idx >= vertex_count))
        r.fail(f"{label} has an index past its {vertex_count} vertices (index {k} is {int(idx[k])})")
    return idx


def _normals(r: _Reader, prim: dict, pos: np.ndarray, idx: np.ndarray, label: str, warn: list[str]) -> np.ndarray:
    nrm = _vertex_data(r, prim, "NORMAL", label, pos.shape[0], ("VEC3",))
    if nrm is None:
        return vertex_normals(pos, idx)
    nrm = nrm.astype(np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        bad = ~np.all(np.isfinite(nrm), axis=1) | ~(np.linalg.norm(nrm, axis=1) > tf.EPS)
    if np.any(bad):
        # Normals are derived data: the triangles say what they should be.
        nrm[bad] = vertex_normals(pos, idx)[bad]
        warn.append(f"{label}: {int(bad.sum())} normals were NaN, infinite or zero length; recomputed from the triangles")
    return nrm


def _colors(r: _Reader, prim: dict, v: int, label: str) -> np.ndarray | None:
    """COLOR_0 as float64 RGBA (None when the primitive has none)."""
    index = _attr(r, prim, "COLOR_0", label)
    if index is None:
        return None
    what = f"accessor {index} ({label} COLOR_0)"
    c = r.accessor(index, f"{label} COLOR_0", ("VEC3", "VEC4")).astype(np.float64)
    if c.shape[0] != v:
        r.fail(f"{label} COLOR_0 must hold one RGB or RGBA colour per vertex, got shape {c.shape}")
    bad = ~np.isfinite(c)
    if np.any(bad):
        r.fail(f"{what}: vertex {_first(bad)} has a NaN or infinite colour")
    return np.concatenate([c, np.ones((v, 1))], axis=1) if c.shape[1] == 3 else c


def _uvs(r: _Reader, prim: dict, surface, materials: Materials, label: str, v: int) -> np.ndarray | None:
    """The texture coordinates of a textured surface (None: untextured, or it has none)."""
    if surface.texture < 0:
        return None
    key = f"TEXCOORD_{surface.texcoord}"
    raw = _vertex_data(r, prim, key, label, v, ("VEC2",))
    return materials.uvs(surface, raw, label, f"accessor {_attr(r, prim, key, label)} ({label} {key})")


def _mode(r: _Reader, prim: dict, label: str) -> int:
    return r.whole(prim, "mode", label, default=4, hi=6)


def _mesh_extras(r: _Reader, extras: dict, label: str) -> tuple[str, int, str]:
    """(piece, lod, group) from a mesh's extras.crowd."""
    lod = extras.get("lod", 0)
    if isinstance(lod, float) and lod.is_integer():
        lod = int(lod)
    if not _is_whole(lod) or not 0 <= lod <= MAX_LOD:
        r.fail(f"{label}: extras.crowd.lod must be a whole number from 0 to {MAX_LOD}, got {_show(lod)}")
    return str(extras.get("piece", label)), lod, str(extras.get("group", ""))


class _Morphs:
    """The character's morph targets, gathered from its skinned meshes: one per target name (a mesh's
    targets, its other primitives' and its LODs' share a name), with the default weight of the first
    mesh that has it. glTF names targets in mesh.extras.targetNames (the exporters' convention, Blender's
    among them); unnamed ones are named after their mesh and number, so they are never merged by accident."""

    def __init__(self, r: _Reader, warn: list[str]):
        self.r, self.warn = r, warn
        self.names: list[str] = []
        self.defaults: list[float] = []
        self._index: dict[str, int] = {}
        self.of_mesh: dict[int, np.ndarray] = {}  # glTF mesh index -> its targets' morph indices

    def mesh(self, mesh_index: int, mesh: dict, node: dict, label: str, count: int) -> np.ndarray:
        """The morph indices of the `count` targets of glTF mesh `mesh_index`, as drawn by `node`."""
        if mesh_index in self.of_mesh:
            return self.of_mesh[mesh_index]
        r = self.r
        where = f"mesh {mesh_index} ({label})"
        names = (mesh.get("extras") or {}).get("targetNames") if isinstance(mesh.get("extras"), dict) else None
        if names is not None and (not isinstance(names, list) or len(names) != count or not all(isinstance(n, str) and n for n in names)):
            self.warn.append(f"{where}: extras.targetNames is not {count} names; its targets are named by number")
            names = None
        base = mesh.get("name") if isinstance(mesh.get("name"), str) and mesh.get("name") else f"mesh{mesh_index}"
        names = list(names) if names else [f"{base}.target{k}" for k in range(count)]
        for k, name in enumerate(names):
            if names.index(name) != k:
                self.warn.append(f"{where}: target {k} has the name {name!r} of target {names.index(name)}; named {name}.{k}")
                names[k] = f"{name}.{k}"
        defaults = r.numbers(mesh, "weights", count, where, np.zeros(count))
        defaults = r.numbers(node, "weights", count, f"the node drawing {where}", defaults)
        big = np.abs(defaults) > MAX_MORPH_WEIGHT
        if np.any(big):
            r.fail(f"{where}: default weight {_first(big)} is {float(defaults[big][0]):.6g}, beyond ±{MAX_MORPH_WEIGHT:g}")
        out = np.empty(count, np.int64)
        for k, (name, weight) in enumerate(zip(names, defaults)):
            if name not in self._index:
                if len(self.names) >= MAX_MORPHS:
                    r.fail(f"{where}: more than the {MAX_MORPHS} morph targets a character may have")
                self._index[name] = len(self.names)
                self.names.append(name)
                self.defaults.append(float(weight))
            elif self.defaults[self._index[name]] != float(weight):
                self.warn.append(f"{where}: target {name!r} has default weight {float(weight):g}, another mesh's "
                                 f"{self.defaults[self._index[name]]:g}; the first is kept")
            out[k] = self._index[name]
        self.of_mesh[mesh_index] = out
        return out


def _target_deltas(r: _Reader, target, key: str, k: int, v: int, label: str) -> np.ndarray | None:
    """Target k's per-vertex differences of `key` (POSITION or NORMAL), float64 (V, 3), or None."""
    index = r.index(target, key, "accessors", f"{label} target {k}")
    if index is None:
        return None
    what = f"accessor {index} ({label} target {k} {key})"
    # glTF and KHR_mesh_quantization: float, or (normalised or not) signed bytes and shorts.
    d = r.accessor(index, f"{label} target {k} {key}", ("VEC3",), (5126, 5120, 5122)).astype(np.float64)
    if d.shape[0] != v:
        r.fail(f"{what} has {d.shape[0]} elements for {v} vertices")
    _refuse_bad_values(r, d, what, "vertex", MAX_COORDINATE, "moves beyond ±{limit:g}")
    return d


def _read_targets(r: _Reader, morphs: _Morphs, mesh_index: int, mesh: dict, node: dict, prim: dict, primitives: list,
                  label: str, v: int, warn: list[str]):
    """A primitive's morph targets: (morph indices, position deltas, normal deltas), or Nones."""
    targets = r.list(prim, "targets", label)
    counts = {len(p.get("targets") or []) if isinstance(p, dict) and isinstance(p.get("targets") or [], list) else -1
              for p in primitives} if prim is primitives[0] else ()  # (once a mesh)
    if len(counts) > 1:
        r.fail(f"mesh {mesh_index}: its primitives have different numbers of morph targets ({', '.join(map(str, sorted(counts)))}); glTF requires one")
    if not targets:
        return None, None, None
    if len(targets) > MAX_MORPHS:
        r.fail(f"{label}: {len(targets):,} morph targets, more than the {MAX_MORPHS} allowed")
    indices = morphs.mesh(mesh_index, mesh, node, label, len(targets))
    # Dense float32 deltas for every target, however sparse the file's: charged before they are made.
    r.charge_bytes(2 * len(targets) * v * 3 * 4, f"{label}'s {len(targets)} morph targets")
    positions, normals = np.zeros((len(targets), v, 3), np.float32), np.zeros((len(targets), v, 3), np.float32)
    others: set[str] = set()
    for k, target in enumerate(targets):
        if not isinstance(target, dict):
            r.fail(f"{label} target {k} is not a JSON object")
        for key, out in (("POSITION", positions), ("NORMAL", normals)):
            d = _target_deltas(r, target, key, k, v, label)
            if d is not None:
                out[k] = d
        others |= set(target) - {"POSITION", "NORMAL"}
    if others:
        warn.append(f"{label}: morph target {', '.join(sorted(map(str, others)))} deltas left out (positions and normals are drawn)")
    return indices, positions, normals


def _read_meshes(r: _Reader, tree: _Tree, skin_maps: dict[int, np.ndarray], materials: Materials, morphs: _Morphs,
                 warn: list[str]) -> list[SkinnedMesh]:
    """The meshes drawn with the merged skins; `skin_maps[k]` maps skin k's joint indices to the skeleton's."""
    meshes: list[SkinnedMesh] = []
    seen_mesh: set[tuple[int, int]] = set()
    read_mesh: set[int] = set()
    for node in tree.nodes:
        mesh_index, skin_index = node.get("mesh"), node.get("skin")
        if mesh_index is None or skin_index not in skin_maps or (mesh_index, skin_index) in seen_mesh:
            continue
        seen_mesh.add((mesh_index, skin_index))
        skin_to_new = skin_maps[skin_index]
        # A mesh drawn with two merged skins is two meshes: the second is named after its skin.
        suffix = f"@skin{skin_index}" if mesh_index in read_mesh else ""
        read_mesh.add(mesh_index)
        mesh = r.item("meshes", mesh_index)
        extras = crowd_extras(mesh)
        mesh_name = mesh.get("name") if isinstance(mesh.get("name"), str) else None
        primitives = r.list(mesh, "primitives", f"mesh {mesh_index}")
        for pi, prim in enumerate(primitives):
            label = mesh_name or f"mesh{mesh_index}"
            if len(primitives) > 1:
                label = f"{label}#{pi}"
            label += suffix
            if not isinstance(prim, dict):
                r.fail(f"{label} is not a JSON object")
            r.count_primitive(label)
            mode = _mode(r, prim, label)
            if mode != 4:
                warn.append(f"{label}: primitive mode {mode} is not triangles; left out")
                continue
            if _attr(r, prim, "POSITION", label) is None:
                r.fail(f"{label} has no POSITION")
            pos = _positions(r, prim, label)
            v = pos.shape[0]
            if _attr(r, prim, "JOINTS_0", label) is None or _attr(r, prim, "WEIGHTS_0", label) is None:
                r.fail(f"{label} is drawn with a skin but has no JOINTS_0/WEIGHTS_0")
            jsets, wsets = [], []
            k = 0
            while _attr(r, prim, f"JOINTS_{k}", label) is not None and _attr(r, prim, f"WEIGHTS_{k}", label) is not None:
                jj = _vertex_data(r, prim, f"JOINTS_{k}", label, v, ("VEC4",), _UNSIGNED)
                ww = _vertex_data(r, prim, f"WEIGHTS_{k}", label, v, ("VEC4",), (5126, 5121, 5123)).astype(np.float64)
                what = f"accessor {_attr(r, prim, f'WEIGHTS_{k}', label)} ({label} WEIGHTS_{k})"
                bad = ~np.isfinite(ww)
                if np.any(bad):
                    r.fail(f"{what}: vertex {_first(bad)} has a NaN or infinite weight")
                negative = ww < -WEIGHT_NOISE
                if np.any(negative):
                    r.fail(f"{what}: vertex {_first(negative)} has a negative weight ({float(ww[negative][0]):.3g})")
                jsets.append(jj.astype(np.int64))
                wsets.append(ww)
                k += 1
            joints = np.concatenate(jsets, axis=1)
            weights = np.concatenate(wsets, axis=1)
            weights = np.maximum(weights, 0.0)
            used = weights > 0.0
            if np.any(joints[used] >= skin_to_new.shape[0]):
                vertex = _first(used & (joints >= skin_to_new.shape[0]))
                r.fail(f"{label} references joint {int(joints[used].max())} but the skin has {skin_to_new.shape[0]} (vertex {vertex})")
            joints = np.where(used, skin_to_new[np.minimum(joints, skin_to_new.shape[0] - 1)], 0)
            if joints.shape[1] > 4:
                order = np.argsort(-weights, axis=1, kind="stable")[:, :4]
                dropped = float(np.max(np.sum(weights, 1) - np.sum(np.take_along_axis(weights, order, 1), 1)))
                joints, weights = np.take_along_axis(joints, order, 1), np.take_along_axis(weights, order, 1)
                warn.append(f"{label}: more than 4 influences per vertex; kept the 4 largest (largest weight dropped {dropped:.3f})")
            total = weights.sum(axis=1, keepdims=True)
            zero = total[:, 0] <= 1e-12
            if np.any(zero):
                warn.append(f"{label}: {int(zero.sum())} vertices have no weight; bound to the first root joint")
                weights[zero] = [1.0, 0.0, 0.0, 0.0]
                joints[zero] = 0
                total = weights.sum(axis=1, keepdims=True)
            weights = weights / total
            idx = _indices(r, prim, v, label, warn)
            if not idx.size:
                warn.append(f"{label}: no whole triangle; left out")
                continue
            nrm = _normals(r, prim, pos, idx, label, warn)
            colors = _colors(r, prim, v, label)
            surface = materials.surface(prim, label)
            uvs = _uvs(r, prim, surface, materials, label, v)
            piece, lod, group = _mesh_extras(r, extras, label)
            morph_targets, morph_positions, morph_normals = _read_targets(r, morphs, mesh_index, mesh, node, prim, primitives, label, v, warn)
            meshes.append(SkinnedMesh(
                name=label, piece=piece, lod=lod,
                positions=pos.astype(np.float32), normals=tf.quat_normalize(np.concatenate([nrm, np.zeros((v, 1))], 1))[:, :3].astype(np.float32),
                joints=joints.astype(np.uint16), weights=weights.astype(np.float32), indices=idx.astype(np.uint32),
                colors=None if colors is None else colors.astype(np.float32), base_color=surface.base_color, group=group,
                texture=surface.texture if uvs is not None else -1, uvs=uvs,
                morph_targets=morph_targets, morph_positions=morph_positions, morph_normals=morph_normals,
            ))
    return meshes


def _rigid_parts(r: _Reader, mesh_index: int, materials: Materials, warn: list[str], textures: bool = True) -> list[RigidMesh]:
    """A rigid mesh as one RigidMesh per base-colour texture its primitives use (untextured ones
    together): each part is then one draw. Each primitive's base colour factor is multiplied into its
    vertex colours, so primitives of different colours keep them in one part."""
    mesh = r.item("meshes", mesh_index)
    mesh_name = mesh.get("name") if isinstance(mesh.get("name"), str) else None
    parts: dict[int, list] = {}  # texture -> [(positions, normals, indices, colours, uvs)]
    for prim in r.list(mesh, "primitives", f"mesh {mesh_index}"):
        label = f"mesh {mesh_name or mesh_index!r}"
        if not isinstance(prim, dict):
            r.fail(f"{label}: a primitive is not a JSON object")
        r.count_primitive(label)
        if _mode(r, prim, label) != 4 or _attr(r, prim, "POSITION", label) is None:
            continue
        targets = r.list(prim, "targets", label)
        if targets:  # a rigid mesh is drawn as it is at rest: its shapes cannot be given weights
            warn.append(f"{label}: a rigid mesh (on a joint, or a prop); its {len(targets)} morph targets left out")
        pos = _positions(r, prim, label)
        idx = _indices(r, prim, pos.shape[0], label, warn)
        if not idx.size:
            continue
        nrm = _normals(r, prim, pos, idx, label, warn)
        surface = materials.surface(prim, label, textures)
        uvs = _uvs(r, prim, surface, materials, label, pos.shape[0])
        colors = _colors(r, prim, pos.shape[0], label)
        colors = (np.ones((pos.shape[0], 4)) if colors is None else colors) * np.asarray(surface.base_color)
        parts.setdefault(surface.texture if uvs is not None else -1, []).append((pos, nrm, idx, colors, uvs))
    if not parts:
        warn.append(f"mesh {mesh_name!r} has no triangles; left out")
        return []
    out = []
    for texture, prims in sorted(parts.items()):
        starts = np.cumsum([0] + [len(p[0]) for p in prims])
        name = mesh_name or f"mesh{mesh_index}"
        out.append(RigidMesh(
            name if len(parts) == 1 else f"{name}#{len(out)}",
            np.concatenate([p[0] for p in prims]).astype(np.float32), np.concatenate([p[1] for p in prims]).astype(np.float32),
            np.concatenate([p[2] + k for p, k in zip(prims, starts)]).astype(np.uint32),
            np.concatenate([p[3] for p in prims]).astype(np.float32), texture=texture,
            uvs=np.concatenate([p[4] for p in prims]).astype(np.float32) if texture >= 0 else None))
    return out


def _untextured(parts: list[RigidMesh]) -> RigidMesh | None:
    """The parts as one untextured mesh (a prop: the weapons stage draws one mesh per prop)."""
    if not parts:
        return None
    starts = np.cumsum([0] + [len(p.positions) for p in parts])
    return RigidMesh(parts[0].name.split("#")[0], np.concatenate([p.positions for p in parts]), np.concatenate([p.normals for p in parts]),
                     np.concatenate([p.indices + k for p, k in zip(parts, starts)]).astype(np.uint32), np.concatenate([p.colors for p in parts]))


def _read_rigid(r: _Reader, tree: _Tree, new_index, factor: float, materials: Materials, warn: list[str]):
    attachments, props = [], {}
    coarser: dict[str, dict[int, RigidMesh]] = {}  # prop → its LOD k >= 1 meshes (extras.crowd prop and lod)
    nodes = tree.nodes
    for ni, node in enumerate(nodes):
        extras = crowd_extras(node)
        if node.get("mesh") is not None and node.get("skin") is None:
            if isinstance(extras.get("prop"), str):
                parts = _rigid_parts(r, node["mesh"], materials, warn, textures=False)
                if any(materials.has_texture(prim) for prim in r.list(r.item("meshes", node["mesh"]), "primitives", "") if isinstance(prim, dict)):
                    warn.append(f"prop {extras['prop']!r}: its texture is left out (props are drawn in their vertex and base colours)")
                mesh = _untextured(parts)
                lod = _mesh_extras(r, extras, r.node_where(ni))[1]
                if lod > 0:
                    if mesh is not None:
                        coarser.setdefault(extras["prop"], {})[lod] = mesh
                    continue
                grip = np.eye(4)
                for c in node.get("children") or []:
                    if crowd_extras(nodes[c]).get("grip") is not None:
                        grip = r.local(c)
                        # The weapons stage places the prop through inverse(grip): it must have one.
                        _check_matrices(r, grip[None], f"{r.node_where(c)} (grip of prop {extras['prop']!r})")
                if mesh is not None:
                    props[extras["prop"]] = Prop(mesh, grip)
                continue
            # The offset from the nearest joint above: the locals of the non-joint nodes between, then its own.
            k = tree.joint_above(ni)
            if k is None:
                name = node.get("name")
                warn.append(f"static mesh {name if isinstance(name, str) and name else ni!r} is not skinned nor under a joint; left out")
                continue
            p = tree.parent[ni]
            offset = r.local(ni) if p == k else tree.run_matrix(p) @ r.local(ni)
            for part in _rigid_parts(r, node["mesh"], materials, warn):
                attachments.append(Attachment(part, new_index[k], np.diag([factor, factor, factor, 1.0]) @ offset))
    for name, by_lod in coarser.items():
        if name not in props:
            warn.append(f"prop {name!r}: coarser LOD meshes but no LOD0 mesh; left out")
            continue
        # LODs in order; a gap (LOD1 and LOD3 only) uses the next finer one in its place.
        lods = [props[name].mesh]
        for lod in range(1, max(by_lod) + 1):
            lods.append(by_lod.get(lod, lods[-1]))
        props[name] = dataclasses.replace(props[name], coarser=tuple(lods[1:]))
    return attachments, props


def _channel_targets(r: _Reader, anims: list) -> list[set]:
    """The target nodes of each animation's channels, with the channels' structure checked."""
    if len(anims) > MAX_ANIMATIONS:
        r.fail(f"{len(anims):,} animations, more than the {MAX_ANIMATIONS:,} allowed")
    out, channels = [], 0
    for ai, anim in enumerate(anims):
        where = f"animation {ai}"
        if not isinstance(anim, dict):
            r.fail(f"{where} is not a JSON object")
        targets = set()
        channels += len(r.list(anim, "channels", where))
        if channels > MAX_CHANNELS:
            r.fail(f"the animations have more than the {MAX_CHANNELS:,} channels allowed")
        for ci, ch in enumerate(r.list(anim, "channels", where)):
            if not isinstance(ch, dict):
                r.fail(f"{where} channel {ci} is not a JSON object")
            target = r.obj(ch, "target", f"{where} channel {ci}")
            if target is not None:
                targets.add(r.index(target, "node", "nodes", f"{where} channel {ci} target"))
        out.append(targets)
    return out


def _read_clips(r: _Reader, tree: _Tree, skeleton: Skeleton, new_index, folds, factor: float, morphs: _Morphs,
                warn: list[str]) -> list[Clip]:
    anims = r.array("animations")
    joint_set = tree.joints
    targets = _channel_targets(r, anims)
    # Old exporters wrote one animation per joint; a set of single-node animations with disjoint
    # targets is one clip split up, so it is merged back.
    merge = len(anims) > 1 and all(len(t) == 1 for t in targets) and len(set().union(*targets)) == len(anims)

    def anim_name(i):
        name = anims[i].get("name")
        return name if isinstance(name, str) and name else None

    groups = [(Path(r.path).stem, list(range(len(anims))))] if merge else [(anim_name(i) or f"clip{i}", [i]) for i in range(len(anims))]
    if merge:
        warn.append(f"merged {len(anims)} single-joint animations (old one-animation-per-joint layout) into one clip")
    clips: list[Clip] = []
    clip_names = set()
    for name, members in groups:
        channels: dict[tuple[int, str], Channel] = {}
        morph_channels: list[MorphChannel] = []
        extras = crowd_extras(anims[members[0]])
        for ai in members:
            anim = anims[ai]
            samplers = r.list(anim, "samplers", f"animation {ai}")
            for ci, ch in enumerate(r.list(anim, "channels", f"animation {ai}")):
                where = f"animation {anim_name(ai) or ai!r} channel {ci}"
                target = ch.get("target")
                if target is None or target.get("node") is None:
                    continue
                node, path = target["node"], target.get("path")
                if path == "weights":
                    channel = _morph_channel(r, anims[ai], ch, node, morphs, where, warn)
                    if channel is not None:
                        channel = _new_morphs(channel, morph_channels, where, warn)
                    if channel is not None:
                        morph_channels.append(channel)
                    continue
                if path not in ("translation", "rotation", "scale"):
                    warn.append(f"{where}: target path {_show(path)} is not a joint transform; left out")
                    continue
                if node not in joint_set:
                    warn.append(f"{where}: animates non-joint node {node}; left out")
                    continue
                j = new_index[node]
                key = (j, path)
                if key in channels:
                    warn.append(f"{where}: second {path} channel for joint {skeleton.names[j]!r}; left out")
                    continue
                si = ch.get("sampler")
                if not _is_whole(si) or not 0 <= si < len(samplers) or not isinstance(samplers[si], dict):
                    r.fail(f"{where} sampler index {_show(si)} is out of range")
                sampler = samplers[si]
                interp = r.choice(sampler, "interpolation", where, ("LINEAR", "STEP", "CUBICSPLINE"), default="LINEAR")
                comps = 4 if path == "rotation" else 3
                input_index = r.index(sampler, "input", "accessors", where, required=True)
                output_index = r.index(sampler, "output", "accessors", where, required=True)
                times = r.accessor(input_index, f"key times of {where}", ("SCALAR",))[:, 0].astype(np.float64)
                values = r.accessor(output_index, f"{path} keys of {where}", ("VEC4",) if comps == 4 else ("VEC3",)).astype(np.float64)
                _check_times(r, times, f"accessor {input_index} (key times of {where})")
                k = times.shape[0]
                want = 3 * k if interp == "CUBICSPLINE" else k
                if values.shape[0] != want:
                    r.fail(f"{where}: {values.shape[0]} output values for {k} keys ({interp})")
                if interp == "CUBICSPLINE":
                    values = values.reshape(k, 3, comps)
                _check_keys(r, path, interp, times, values, f"accessor {output_index} ({path} keys of {where})")
                values = _convert_keys(path, values, interp, folds[j], factor, skeleton.parents[j] < 0)
                channels[key] = Channel(j, path, interp, times, values)
        if not channels and not morph_channels:
            warn.append(f"animation {name!r} animates no joint of the skin and no morph target; left out")
            continue
        chans = sorted(channels.values(), key=lambda c: (c.joint, c.path))
        start = min(float(c.times[0]) for c in (*chans, *morph_channels))
        end = max(float(c.times[-1]) for c in (*chans, *morph_channels))
        if end - start > MAX_CLIP_SECONDS:
            r.fail(f"animation {name!r} lasts {end - start:.3g} s, more than the {MAX_CLIP_SECONDS:g} s a clip may last")
        clip = Clip(name, chans, start, end, False, {}, None, morph_channels)
        loop = extras.get("loop")
        clip.loop = bool(loop) if isinstance(loop, bool) else _looks_looped(skeleton, clip)
        markers = extras.get("markers")
        if isinstance(markers, dict):
            if not all(_is_number(v) for v in markers.values()):
                r.fail(f"animation {name!r}: extras.crowd.markers must map names to phases, got {_show(markers)}")
            clip.markers = {str(k): float(v) for k, v in markers.items()}
        stride = extras.get("stride")
        if _is_number(stride):
            if not 0.0 < stride <= MAX_COORDINATE:  # NaN fails this too
                r.fail(f"animation {name!r}: extras.crowd.stride must be a length from 0 to {MAX_COORDINATE:g}, got {_show(stride)}")
            clip.stride = float(stride)
        base, n = clip.name, 1
        while clip.name in clip_names:
            n += 1
            clip.name = f"{base}.{n}"
        clip_names.add(clip.name)
        clips.append(clip)
    return clips


def _morph_channel(r: _Reader, anim: dict, ch: dict, node: int, morphs: _Morphs, where: str, warn: list[str]) -> MorphChannel | None:
    """A `weights` channel: the weights of the targets of the mesh `node` draws, N a key (glTF: the
    output holds K * N values, or 3 * K * N for CUBICSPLINE, key by key)."""
    mesh_index = r.item("nodes", node).get("mesh")
    indices = morphs.of_mesh.get(mesh_index) if _is_whole(mesh_index) else None
    if indices is None:
        warn.append(f"{where}: animates the morph weights of node {node}, which draws no skinned mesh with morph targets; left out")
        return None
    samplers = r.list(anim, "samplers", where)
    si = ch.get("sampler")
    if not _is_whole(si) or not 0 <= si < len(samplers) or not isinstance(samplers[si], dict):
        r.fail(f"{where} sampler index {_show(si)} is out of range")
    sampler = samplers[si]
    interp = r.choice(sampler, "interpolation", where, ("LINEAR", "STEP", "CUBICSPLINE"), default="LINEAR")
    input_index = r.index(sampler, "input", "accessors", where, required=True)
    output_index = r.index(sampler, "output", "accessors", where, required=True)
    times = r.accessor(input_index, f"key times of {where}", ("SCALAR",))[:, 0].astype(np.float64)
    _check_times(r, times, f"accessor {input_index} (key times of {where})")
    what = f"accessor {output_index} (morph weights of {where})"
    values = r.accessor(output_index, f"morph weights of {where}", ("SCALAR",), (5126, 5120, 5121, 5122, 5123))[:, 0].astype(np.float64)
    k, n = times.shape[0], indices.shape[0]
    want = (3 if interp == "CUBICSPLINE" else 1) * k * n
    if values.shape[0] != want:
        r.fail(f"{what}: {values.shape[0]} weights for {k} keys of {n} targets ({interp}: {want})")
    _refuse_bad_values(r, values, what, "weight", MAX_MORPH_WEIGHT, "is {value:.6g}, beyond ±{limit:g}")
    values = values.reshape((k, 3, n) if interp == "CUBICSPLINE" else (k, n))
    return MorphChannel(indices.copy(), interp, times, values)


def _new_morphs(channel: MorphChannel, kept: list[MorphChannel], where: str, warn: list[str]) -> MorphChannel | None:
    """What `channel` adds to the clip's `kept` channels: the targets none of them drives. A mesh's nodes
    (its LODs, its pieces) share targets by name, and each node's channel drives them: where they say the
    same (keys, interpolation and weights), the repeat is dropped silently; where they differ, the first
    stays, with a warning."""
    fresh = np.ones(len(channel.morphs), bool)
    for other in kept:
        common, mine, theirs = np.intersect1d(channel.morphs, other.morphs, return_indices=True)
        if not len(common):
            continue
        same = (other.interpolation == channel.interpolation and np.array_equal(other.times, channel.times)
                and np.array_equal(other.values[..., theirs], channel.values[..., mine]))
        if not same:
            warn.append(f"{where}: keys morph targets another weights channel of the clip keys otherwise; the first is kept")
        fresh[mine] = False
    if fresh.all():
        return channel
    if not fresh.any():
        return None
    return MorphChannel(channel.morphs[fresh], channel.interpolation, channel.times, channel.values[..., fresh])


def _check_times(r: _Reader, times: np.ndarray, what: str) -> None:
    """glTF: key times are seconds, times[0] >= 0, strictly increasing."""
    _refuse_bad_values(r, times, what, "key")
    if times[0] < 0.0:
        r.fail(f"{what}: key 0 is at {times[0]:.6g} s; glTF key times start at 0 or later")
    step = np.diff(times) <= 0.0
    if np.any(step):
        k = _first(step)
        r.fail(f"{what}: key times do not increase (key {k + 1} at {times[k + 1]:.6g} s follows {times[k]:.6g} s)")


def _check_keys(r: _Reader, path: str, interp: str, times: np.ndarray, values: np.ndarray, what: str) -> None:
    """Key values (K, C), or (K, 3, C) for CUBICSPLINE, that the stages can draw."""
    _refuse_bad_values(r, values, what, "key")
    keys = values[:, 1] if interp == "CUBICSPLINE" else values
    if path == "rotation":
        zero = np.linalg.norm(keys, axis=-1) < ZERO_QUATERNION
        if np.any(zero):
            r.fail(f"{what}: key {_first(zero)} is the zero quaternion")
        if interp == "CUBICSPLINE" and len(times) > 1:
            if np.max(np.abs(values)) > MAX_SCALE:
                r.fail(f"{what}: key {_first(np.abs(values) > MAX_SCALE)} has a value or tangent beyond ±{MAX_SCALE:g}")
            # The spline is normalised after evaluation: it must not pass through zero between keys.
            u = np.linspace(0.0, 1.0, 9)[1:-1, None, None]
            span = np.diff(times)[None, :, None]
            u2, u3 = u * u, u * u * u
            q = ((2 * u3 - 3 * u2 + 1) * values[:-1, 1] + (u3 - 2 * u2 + u) * span * values[:-1, 2]
                 + (-2 * u3 + 3 * u2) * values[1:, 1] + (u3 - u2) * span * values[1:, 0])
            low = np.linalg.norm(q, axis=-1).min(axis=0) < ZERO_QUATERNION
            if np.any(low):
                k = int(np.argmax(low))
                r.fail(f"{what}: the spline between keys {k} and {k + 1} passes through the zero quaternion")
        return
    _refuse_bad_values(r, values, what, "key", MAX_COORDINATE if path == "translation" else MAX_SCALE)


def _check_scale_chains(r: _Reader, skeleton: Skeleton, clips: list[Clip]) -> None:
    """The largest scale each joint reaches (rest and keys, spline overshoot bounded), multiplied down
    every chain, stays within MAX_SCALE: past it a float32 skinning matrix overflows a few joints down."""
    largest = np.max(np.abs(skeleton.rest_scale), axis=1)
    for clip in clips:
        for ch in clip.channels:
            if ch.path != "scale":
                continue
            if ch.interpolation == "CUBICSPLINE":
                span = float(np.max(np.diff(ch.times))) if ch.times.shape[0] > 1 else 0.0
                peak = float(np.max(np.abs(ch.values[:, 1]))) + 0.3 * span * float(np.max(np.abs(ch.values[:, 0::2])))
            else:
                peak = float(np.max(np.abs(ch.values)))
            largest[ch.joint] = max(largest[ch.joint], peak)
    chain = np.empty_like(largest)
    for j, p in enumerate(skeleton.parents):
        chain[j] = largest[j] * (chain[p] if p >= 0 else 1.0)
        if chain[j] > MAX_SCALE:
            r.fail(f"joint {skeleton.names[j]!r}: the scales down its chain multiply to {chain[j]:.3g}, beyond {MAX_SCALE:g}")


def _convert_keys(path: str, values: np.ndarray, interp: str, fold: _Fold | None, factor: float, is_root: bool) -> np.ndarray:
    if path == "rotation":
        if interp != "CUBICSPLINE":  # spline keys are normalised after evaluation, not before
            values = tf.quat_normalize(values)
        if fold is not None:
            values = _apply_channel(values, interp, lambda v, tangent: fold.rotation(v))
        return values
    if path == "translation":
        if fold is not None:
            values = _apply_channel(values, interp, lambda v, tangent: fold.translation(v, tangent))
        if not is_root and factor != 1.0:
            values = values * factor
        return values
    if fold is not None:
        values = _apply_channel(values, interp, lambda v, tangent: fold.scale(v))
    if is_root and factor != 1.0:
        values = values / factor
    return values


def _looks_looped(skeleton: Skeleton, clip: Clip) -> bool:
    if clip.duration <= 0.0:
        return False
    pose = sample_clip(skeleton, clip, np.array([0.0, 1.0]))
    dq = np.abs(np.sum(pose.rotation[0] * pose.rotation[1], axis=-1))
    angle = 2.0 * np.arccos(np.clip(dq, 0.0, 1.0))
    moved = np.linalg.norm(pose.translation[0] - pose.translation[1], axis=-1)
    # Root translation is excluded: locomotion clips with root motion still loop.
    moved[skeleton.parents < 0] = 0.0
    return bool(np.max(angle) < LOOP_ANGLE_TOLERANCE and np.max(moved) < LOOP_DISTANCE_TOLERANCE)
