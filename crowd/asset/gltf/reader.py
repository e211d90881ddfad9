"""The glTF file as checked JSON and buffers: the container, typed access to every property, accessors,
node transforms, and the limits and value checks every part of the import shares.

Why the importer parses glTF itself, while the writer (gltf_write) keeps pygltflib: reading is where a
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
  (tree.MAX_NODES, skins.MAX_JOINTS, clips.MAX_ANIMATIONS and MAX_CHANNELS, MAX_PRIMITIVES), one accessor as the
  float64 values the importer makes of it (MAX_ACCESSOR_BYTES), all accessor reads of one import
  (MAX_DECODED_BYTES), meshopt-compressed bufferViews (MAX_MESHOPT_BYTES), a clip's length
  (clips.MAX_CLIP_SECONDS); every walk over the node tree is linear in the number of nodes, so a file at
  every bound at once imports in about 10 s, plus the meshopt decoder's slowest streams at their budget
  (docs/BENCHMARKS.md, "meshopt decoded by hand");
- external buffers must be regular files inside the model's folder: nothing else is opened;
- alignment (byteOffset a multiple of the component size, byteStride of 4) is not enforced: it matters
  to a GPU reading the buffer in place, and here bytes are copied into fresh arrays;
- what the checks still miss meets a safety net that turns it into a one-line GltfImportError too
  (with words the hostile-file tests look for, so a miss fails CI instead of hiding).
"""

from __future__ import annotations

import base64
import binascii
import json
import struct
from pathlib import Path
from typing import NoReturn
from urllib.parse import unquote

import numpy as np

from ...errors import CrowdError
from ... import transforms as tf
from . import meshopt

_COMPONENT = {5120: np.dtype("<i1"), 5121: np.dtype("<u1"), 5122: np.dtype("<i2"), 5123: np.dtype("<u2"),
              5125: np.dtype("<u4"), 5126: np.dtype("<f4")}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
FLOAT_TYPES, UNSIGNED_TYPES = (5126,), (5121, 5123, 5125)
_SINGULAR = {"accessors": "accessor", "bufferViews": "bufferView", "buffers": "buffer", "nodes": "node",
             "meshes": "mesh", "skins": "skin", "animations": "animation", "materials": "material",
             "textures": "texture", "images": "image", "samplers": "sampler"}

# Budgets: far above any character file (the built-in zombie is 0.76 MB, 10,511 JSON values; the largest
# sample, Quaternius' Matt, 1.8 MB and 30,661), far below what exhausts a small CI machine.
MAX_FILE_BYTES = 1 << 30  # the model file and every buffer it loads, together
MAX_JSON_VALUES = 4_000_000  # json.loads makes an object of each: a few hundred MB at most
MAX_PRIMITIVES = 1 << 14  # primitives read, skinned and rigid (a rigid mesh is read once per node using it)
MAX_ACCESSOR_BYTES = 256 << 20  # one accessor, as the float64 values the importer makes of it
MAX_DECODED_BYTES = 1 << 30  # every accessor read of one import, together
MAX_MESHOPT_BYTES = 256 << 20  # bufferViews decoded from meshopt compression, together (crowd-bench meshopt times the bound)
MESHOPT_INDEX_BYTES = 16  # what a decoded index counts against it: the slowest triangles then take about as long as the slowest attributes
# Values the stages can draw (float32 on the GPU, a shadow map around the crowd).
MAX_COORDINATE = 1e6  # positions and translations, in the file's units (metres)
MAX_SCALE = 1e6  # one scale component, and the product of the largest scales along a joint chain
MAX_MORPH_WEIGHT = 10.0  # a morph weight, keyed or default: glTF allows any (overshoots, negative correctives)
ZERO_QUATERNION = 1e-6  # a rotation this short has no direction (int16-normalised keys are >= 3e-5)
AFFINE_TOLERANCE = 1e-4  # a matrix's last row against (0, 0, 0, 1)
_SAFE_EXTENSION_PREFIXES = ("KHR_materials_", "KHR_texture_", "EXT_texture_", "KHR_lights_", "KHR_xmp")
_SAFE_EXTENSIONS = {"KHR_mesh_quantization"}  # any component type is read as numbers: that is all it asks
DRACO = "KHR_draco_mesh_compression"  # decoded by DracoPy, the optional extra crowd[draco] (crowd.asset.gltf.draco)


class GltfImportError(CrowdError, ValueError):
    """A file the importer cannot turn into a correct character. The message is one line."""


def one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0][:200] if text else type(exc).__name__


def show(value) -> str:
    """A JSON value for a one-line message: short, newlines escaped."""
    try:
        text = repr(value)
    except ValueError:  # an int past Python's digit limit
        return f"a {type(value).__name__}"
    return text if len(text) <= 48 else text[:45] + "..."


def is_whole(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def first_row(mask: np.ndarray) -> int:
    """Index of the first row with a True anywhere (rows are the leading axis)."""
    return int(np.argmax(mask.reshape(mask.shape[0], -1).any(axis=1)))


class Reader:
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
            if not isinstance(ext, str) or not (ext in _SAFE_EXTENSIONS or ext in (DRACO, *meshopt.EXTENSIONS)
                                                or ext.startswith(_SAFE_EXTENSION_PREFIXES)):
                self.fail(f"requires extension {show(ext)}, which this importer does not implement")
        self._buffers: dict[int, bytes] = {}
        self._unpacked: dict[int, bytes] = {}  # bufferView -> its bytes decoded from meshopt compression
        self._meshopt_bytes = 0
        self._cache: dict[int, np.ndarray] = {}
        self.decoded: dict[int, np.ndarray] = {}  # accessor -> its elements as a compressed primitive decoded them (crowd.asset.gltf.draco)
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
            self.fail(f"not a readable glTF file ({one_line(exc)})")
        if not isinstance(doc, dict):
            self.fail("not a readable glTF file (the JSON is not an object)")
        return doc, blob

    # -- typed access to the JSON

    def array(self, name: str) -> list:
        value = self.doc.get(name)
        if value is None:
            return []
        if not isinstance(value, list):
            self.fail(f"{name!r} must be an array, got {show(value)}")
        return value

    def item(self, name: str, index, kind: str | None = None) -> dict:
        seq = self.array(name)
        kind = kind or _SINGULAR[name]
        if not is_whole(index) or not 0 <= index < len(seq):
            self.fail(f"{kind} index {show(index)} is out of range")
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
        if not is_whole(v) or v < lo or (hi is not None and v > hi):
            bounds = f"from {lo} to {hi}" if hi is not None else f"of at least {lo}"
            self.fail(f"{where}: {key} must be a whole number {bounds}, got {show(v)}")
        return v

    def index(self, obj: dict, key: str, name: str, where: str, required=False):
        v = obj.get(key)
        if v is None:
            if required:
                self.fail(f"{where} has no {key}")
            return None
        n = len(self.array(name))
        if not is_whole(v) or not 0 <= v < n:
            self.fail(f"{where}: {key} {show(v)} is out of range (the file has {n} {name})")
        return v

    def obj(self, obj: dict, key: str, where: str) -> dict | None:
        v = obj.get(key)
        if v is not None and not isinstance(v, dict):
            self.fail(f"{where}: {key} must be a JSON object, got {show(v)}")
        return v

    def list(self, obj: dict, key: str, where: str) -> list:
        v = obj.get(key)
        if v is None:
            return []
        if not isinstance(v, list):
            self.fail(f"{where}: {key} must be an array, got {show(v)}")
        return v

    def choice(self, obj: dict, key: str, where: str, choices, default=None):
        v = obj.get(key, default)
        if v not in choices or not isinstance(v, str):
            self.fail(f"{where}: {key} must be one of {', '.join(choices)}, got {show(v)}")
        return v

    def numbers(self, obj: dict, key: str, n: int, where: str, default) -> np.ndarray:
        v = obj.get(key)
        if v is None:
            return np.array(default, dtype=np.float64)
        if not isinstance(v, list) or len(v) != n or not all(is_number(x) for x in v):
            self.fail(f"{where}: {key} must be {n} numbers, got {show(v)}")
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
            self.fail(f"{where}: uri must be a string, got {show(uri)}")
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
            self.fail(f"{where} uri {show(uri)} is not a usable path")
        if folder != target and folder not in target.parents:
            self.fail(f"{where} uri {show(uri)} points outside the file's folder")
        try:
            if not target.exists():
                self.fail(f"{where} file {show(uri)} is missing from the model's folder")
            if not target.is_file():  # a FIFO or a device would block or never end
                self.fail(f"{where} file {show(uri)} is not a regular file in the model's folder")
            return self._read_file(target, f"{where} file {show(uri)}")
        except OSError as exc:
            self.fail(f"{where} file {show(uri)} cannot be read ({exc.strerror})")

    def view(self, index: int) -> tuple[bytes, int, int, int | None]:
        """(buffer bytes, the view's first byte, its byteLength, its byteStride or None)."""
        v = self.item("bufferViews", index)
        where = f"bufferView {index}"
        buffer = self.index(v, "buffer", "buffers", where, required=True)
        start = self.whole(v, "byteOffset", where, default=0)
        length = self.whole(v, "byteLength", where, lo=1, required=True)
        stride = v.get("byteStride")
        stride = 0 if stride is None else stride  # 0: tightly packed (glTF 1.0 files wrote it)
        if not is_whole(stride) or not (stride == 0 or 4 <= stride <= 252):
            self.fail(f"{where}: byteStride must be a whole number from 4 to 252, got {show(stride)}")
        packed = [name for name in meshopt.EXTENSIONS if name in (self.obj(v, "extensions", where) or {})]
        if packed:
            # The view's own buffer is then a fallback that need hold no bytes: only its declared length counts.
            if start + length > self.whole(self.item("buffers", buffer), "byteLength", f"buffer {buffer}", lo=1, required=True):
                self.fail(f"{where} runs past the end of buffer {buffer}")
            return self._unpack(index, v, packed, length, stride), 0, length, stride or None
        data, buffer_length = self.buffer(buffer)
        if start + length > buffer_length:
            self.fail(f"{where} runs past the end of buffer {buffer}")
        return data, start, length, stride or None

    def _unpack(self, index: int, view: dict, names: list[str], length: int, stride: int) -> bytes:
        """The bytes of a bufferView compressed with meshoptimizer's codecs (crowd.asset.gltf.meshopt)."""
        if index in self._unpacked:
            return self._unpacked[index]
        if len(names) > 1:
            self.fail(f"bufferView {index} uses both {names[0]} and {names[1]}, which the KHR extension forbids")
        where = f"bufferView {index} {names[0]}"
        ext = self.obj(view["extensions"], names[0], where) or self.fail(f"{where} must be an object")
        count = self.whole(ext, "count", where, lo=1, required=True)
        packed_stride = self.whole(ext, "byteStride", where, lo=1, required=True)
        if stride and stride != packed_stride:
            self.fail(f"{where}: byteStride {packed_stride} is not the bufferView's {stride}")
        mode = self.choice(ext, "mode", where, meshopt.MODES)
        filt = self.choice(ext, "filter", where, meshopt.FILTERS, default="NONE")
        source = self.index(ext, "buffer", "buffers", where, required=True)
        start = self.whole(ext, "byteOffset", where, default=0)
        size = self.whole(ext, "byteLength", where, lo=1, required=True)
        data, buffer_length = self.buffer(source)
        if start + size > buffer_length:
            self.fail(f"{where} runs past the end of buffer {source}")
        try:
            meshopt.check_layout(names[0], count, packed_stride, mode, filt, length)
            # Decoding steps in Python per group of 16 bytes and per triangle: its own budget bounds the time.
            self._meshopt_bytes += length if mode == "ATTRIBUTES" else MESHOPT_INDEX_BYTES * count
            if self._meshopt_bytes > MAX_MESHOPT_BYTES:
                self.fail(f"{where} brings the meshopt data decoded to {self._meshopt_bytes:,} bytes "
                          f"(an index counted as {MESHOPT_INDEX_BYTES}), more than the {MAX_MESHOPT_BYTES:,} allowed")
            self.charge_bytes(length, where)
            decoded = meshopt.decode(bytes(data[start:start + size]), count, packed_stride, mode, filt, names[0] == meshopt.EXTENSIONS[1])
        except meshopt.MeshoptError as exc:
            self.fail(f"{where}: {exc}")
        self._unpacked[index] = decoded
        return decoded

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
        if not is_whole(ctype) or ctype not in _COMPONENT:
            self.fail(f"{what} has unknown componentType {show(ctype)}")
        kind = acc.get("type")
        if not isinstance(kind, str) or kind not in _NCOMP:
            self.fail(f"{what} has unknown type {show(kind)}")
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
            self.fail(f"{what}: normalized must be true or false, got {show(normalized)}")
        if normalized and ctype in (5125, 5126):
            self.fail(f"{what} is {'float' if ctype == 5126 else 'unsigned int'} and normalized, which glTF forbids")
        view = self.index(acc, "bufferView", "bufferViews", what)
        if index in self.decoded:
            arr = self.decoded[index]
            if arr.shape != (count, ncomp):
                self.fail(f"{what}: the compressed data decoded to {arr.shape[0]:,} x {arr.shape[1]} values, the accessor says {count:,} x {ncomp}")
            arr = arr.astype(dtype, copy=False)
        elif view is None:
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
        if idx_type not in UNSIGNED_TYPES or not is_whole(idx_type):
            self.fail(f"{where} indices have componentType {show(idx_type)}; glTF allows 5121, 5123, 5125")
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


def crowd_extras(obj) -> dict:
    """A node's or mesh's ``extras.crowd`` (piece, lod, group, socket, prop), or {} when it has none.
    `obj` is a JSON object (dict) or a pygltflib object."""
    extras = obj.get("extras") if isinstance(obj, dict) else getattr(obj, "extras", None)
    if isinstance(extras, dict) and isinstance(extras.get("crowd"), dict):
        return extras["crowd"]
    return {}


def refuse_bad_values(r: Reader, a: np.ndarray, what: str, item: str, limit: float | None = None,
                      beyond: str = "lies beyond ±{limit:g}") -> None:
    """Refuse, naming the first row (`item` i), a NaN or infinite value, or one beyond ±`limit` (then
    `beyond` says how, given the value and the limit)."""
    bad = ~np.isfinite(a)
    if np.any(bad):
        r.fail(f"{what}: {item} {first_row(bad)} is NaN or infinite")
    if limit is not None:
        far = np.abs(a) > limit
        if np.any(far):
            r.fail(f"{what}: {item} {first_row(far)} " + beyond.format(value=float(a[far][0]), limit=limit))


def check_matrices(r: Reader, m: np.ndarray, what: str) -> None:
    """(N, 4, 4) row-major matrices: finite, bounded, affine, invertible."""
    def name(mask):
        return "the matrix" if m.shape[0] == 1 else f"matrix {first_row(mask)}"

    bad = ~np.isfinite(m)
    if np.any(bad):
        r.fail(f"{what}: {name(bad)} holds NaN or infinity")
    big = np.abs(m) > max(MAX_COORDINATE, MAX_SCALE)
    if np.any(big):
        r.fail(f"{what}: {name(big)} holds a value beyond ±{max(MAX_COORDINATE, MAX_SCALE):g}")
    skew = np.abs(m[:, 3] - [0.0, 0.0, 0.0, 1.0]) > AFFINE_TOLERANCE
    if np.any(skew):
        r.fail(f"{what}: {name(skew)} is not affine (its last row is {m[first_row(skew), 3].tolist()})")
    singular = np.abs(np.linalg.det(m[:, :3, :3])) < 1e-18
    if np.any(singular):
        r.fail(f"{what}: {name(singular)} is singular")

