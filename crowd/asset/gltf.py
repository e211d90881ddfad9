"""Import stage: a skinned glTF 2.0 character (.glb or .gltf) → ``Character``, through pygltflib.

Contract: ``load_character(path, clips=None)`` returns a validated ``Character`` whose skeleton is
sorted parents-first, or raises ``GltfImportError`` with one line that names the file and the culprit.
Whatever is read but cannot be used (morph targets, textures, extra skins, static meshes) is listed in
``character.warnings``; nothing is dropped silently.

Space: skinned vertices stay in the mesh's bind space (glTF ignores a skinned mesh node's transform).
Non-joint nodes above and between joints are folded into the joints' local transforms, and a constant
uniform scale above the root joint (0.01 and 100 are common) is factored out of the whole skeleton by
scaling joint translations, so joint transforms come out rigid and in the file's scene units.
"""

from __future__ import annotations

import base64
import binascii
import warnings as _warnings
from pathlib import Path

import numpy as np
import pygltflib as g

from .. import transforms as tf
from .pose import sample_clip
from .model import Attachment, Channel, Character, Clip, ModelError, Prop, RigidMesh, Skeleton, SkinnedMesh, vertex_normals

_COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
LOOP_ANGLE_TOLERANCE = np.radians(2.0)  # first and last pose this close → the clip loops
LOOP_DISTANCE_TOLERANCE = 0.01


class GltfImportError(ValueError):
    """A file the importer cannot turn into a correct character. The message is one line."""


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


class _Reader:
    def __init__(self, path: Path):
        self.path = path
        self.where = path.name
        try:
            with _warnings.catch_warnings():
                _warnings.simplefilter("ignore")
                self.gltf = g.GLTF2().load(str(path))
        except Exception as exc:  # pygltflib raises whatever json/struct/dataclasses raise
            raise GltfImportError(f"{self.where}: not a readable glTF file ({_one_line(exc)})") from None
        if self.gltf is None:
            raise GltfImportError(f"{self.where}: not a readable glTF file")
        version = (self.gltf.asset.version if self.gltf.asset else None) or ""
        if not str(version).startswith("2"):
            raise GltfImportError(f"{self.where}: glTF version {version!r} is not 2.x")
        self._buffers: dict[int, bytes] = {}
        self._cache: dict[int, np.ndarray] = {}

    def fail(self, msg: str):
        raise GltfImportError(f"{self.where}: {msg}")

    def get(self, seq, index, kind):
        if index is None or not isinstance(index, int) or not 0 <= index < len(seq or []):
            self.fail(f"{kind} index {index!r} is out of range")
        return seq[index]

    def buffer(self, index: int) -> bytes:
        if index in self._buffers:
            return self._buffers[index]
        buf = self.get(self.gltf.buffers, index, "buffer")
        uri = buf.uri
        if uri is None:
            data = self.gltf.binary_blob()
            if data is None:
                self.fail(f"buffer {index} has no uri and the file has no binary chunk")
        elif uri.startswith("data:"):
            try:
                data = base64.b64decode(uri.split(",", 1)[1], validate=False)
            except (IndexError, binascii.Error, ValueError):
                self.fail(f"buffer {index} has a malformed data URI")
        else:
            folder = self.path.parent.resolve()
            from urllib.parse import unquote

            target = (folder / unquote(uri)).resolve()
            if folder != target and folder not in target.parents:
                self.fail(f"buffer {index} uri {uri!r} points outside the file's folder")
            try:
                data = target.read_bytes()
            except OSError as exc:
                self.fail(f"buffer {index} file {uri!r} cannot be read ({exc.strerror})")
        if buf.byteLength is not None and len(data) < buf.byteLength:
            self.fail(f"buffer {index} holds {len(data)} bytes, byteLength says {buf.byteLength}")
        self._buffers[index] = data
        return data

    def _view_array(self, view_index: int, offset: int, count: int, dtype, ncomp: int, what: str) -> np.ndarray:
        view = self.get(self.gltf.bufferViews, view_index, "bufferView")
        data = self.buffer(view.buffer)
        base = (view.byteOffset or 0)
        if base + view.byteLength > len(data):
            self.fail(f"bufferView {view_index} runs past the end of buffer {view.buffer}")
        item = np.dtype(dtype).itemsize * ncomp
        stride = view.byteStride or item
        if stride < item:
            self.fail(f"{what}: byteStride {stride} is smaller than an element ({item} bytes)")
        need = offset + stride * (count - 1) + item if count else 0
        if need > view.byteLength:
            self.fail(f"{what} reads {need} bytes from bufferView {view_index} of {view.byteLength}")
        if count == 0:
            return np.zeros((0, ncomp), dtype=dtype)
        raw = np.frombuffer(data, dtype=np.uint8, count=view.byteLength, offset=base)
        # Interleaved views: walk the view with its stride, then copy into a packed array.
        rows = np.lib.stride_tricks.as_strided(raw[offset:], shape=(count, item), strides=(stride, 1))
        return np.ascontiguousarray(rows).view(dtype).reshape(count, ncomp)

    def accessor(self, index: int, what: str = "accessor") -> np.ndarray:
        """Accessor data as (count, ncomp); normalised integers become float64 per the spec."""
        if index in self._cache:
            return self._cache[index]
        acc = self.get(self.gltf.accessors, index, "accessor")
        what = f"{what} (accessor {index})"
        if acc.componentType not in _COMPONENT:
            self.fail(f"{what} has unknown componentType {acc.componentType}")
        if acc.type not in _NCOMP:
            self.fail(f"{what} has unknown type {acc.type!r}")
        dtype, ncomp = _COMPONENT[acc.componentType], _NCOMP[acc.type]
        count = acc.count or 0
        if acc.bufferView is None:
            arr = np.zeros((count, ncomp), dtype=dtype)
        else:
            arr = self._view_array(acc.bufferView, acc.byteOffset or 0, count, dtype, ncomp, what).copy()
        if acc.sparse is not None and acc.sparse.count:
            sp = acc.sparse
            idx_dtype = _COMPONENT.get(sp.indices.componentType)
            if idx_dtype is None:
                self.fail(f"{what}: sparse indices have componentType {sp.indices.componentType}")
            idx = self._view_array(sp.indices.bufferView, sp.indices.byteOffset or 0, sp.count, idx_dtype, 1, what)[:, 0]
            vals = self._view_array(sp.values.bufferView, sp.values.byteOffset or 0, sp.count, dtype, ncomp, what)
            if idx.size and int(idx.max()) >= count:
                self.fail(f"{what}: a sparse index points past the accessor's {count} elements")
            arr[idx.astype(np.int64)] = vals
        if acc.normalized:
            if dtype == np.float32:
                self.fail(f"{what} is float and normalized, which glTF forbids")
            info = np.iinfo(dtype)
            arr = np.maximum(arr.astype(np.float64) / info.max, -1.0)
        self._cache[index] = arr
        return arr


def _node_trs_fields(node):
    """A node's TRS fields with glTF's defaults (rotation normalised)."""
    t = np.array(node.translation if node.translation is not None else [0, 0, 0], dtype=np.float64)
    q = np.array(node.rotation if node.rotation is not None else [0, 0, 0, 1], dtype=np.float64)
    s = np.array(node.scale if node.scale is not None else [1, 1, 1], dtype=np.float64)
    return t, tf.quat_normalize(q), s


def _has_matrix(node) -> bool:
    return node.matrix is not None and len(node.matrix) == 16


def node_local_matrix(node) -> np.ndarray:
    """A pygltflib node's local transform as a float64 4x4 (its matrix, or its TRS with glTF's defaults)."""
    if _has_matrix(node):
        return np.array(node.matrix, dtype=np.float64).reshape(4, 4).T  # glTF matrices are column-major
    return tf.trs_to_mat4(*_node_trs_fields(node))


def _node_trs(node):
    """(t, q, s, shear): a `matrix` node is decomposed, and shear says how far TRS is from it."""
    if _has_matrix(node):
        t, q, s, shear = tf.mat4_decompose(node_local_matrix(node))
        return t, q, s, float(shear)
    return (*_node_trs_fields(node), 0.0)


def crowd_extras(obj) -> dict:
    """A node's or mesh's ``extras.crowd`` (piece, lod, group, socket, prop), or {} when it has none."""
    extras = getattr(obj, "extras", None)
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


def load_character(path: str | Path | None = None, clips: list[str] | None = None) -> Character:
    """Import a skinned character. ``path=None`` loads the built-in zombie; ``clips`` keeps only those clips."""
    if path is None:
        from .zombie import ASSET_PATH, build_character

        path = ASSET_PATH
        if not path.exists():  # a copy that lost the shipped file (wheels carry it): the generator is the source of truth
            return _select_clips(build_character(), clips, "built-in zombie")
    path = Path(path)
    if not path.is_file():
        raise GltfImportError(f"{path}: no such file")
    try:
        character = _import(_Reader(path))
    except ModelError as exc:
        raise GltfImportError(f"{path.name}: {exc}") from None
    return _select_clips(character, clips, path.name)


def _select_clips(character: Character, clips, where: str) -> Character:
    if clips is None:
        return character
    names = [c.name for c in character.clips]
    missing = [c for c in clips if c not in names]
    if missing:
        raise GltfImportError(f"{where}: no clip named {', '.join(map(repr, missing))}; clips are {', '.join(names)}")
    character.clips = [character.clip(c) for c in clips]
    return character


def _import(r: _Reader) -> Character:
    gl = r.gltf
    nodes = gl.nodes or []
    warn: list[str] = []
    parent = {}
    for i, n in enumerate(nodes):
        for c in n.children or []:
            if not isinstance(c, int) or not 0 <= c < len(nodes):
                r.fail(f"node {i} has child {c!r} out of range")
            if c in parent:
                r.fail(f"node {c} has two parents")
            parent[c] = i
    for i in range(len(nodes)):  # cycles
        seen, k = set(), i
        while k in parent:
            if k in seen:
                r.fail(f"node hierarchy has a cycle through node {i}")
            seen.add(k)
            k = parent[k]

    if not gl.skins:
        r.fail("no skin: this importer needs a skinned character")
    skin_use: dict[int, int] = {}
    for n in nodes:
        if n.mesh is not None and n.skin is not None:
            skin_use[n.skin] = skin_use.get(n.skin, 0) + 1
    if not skin_use:
        r.fail("no node draws a mesh with a skin")
    skin_index = max(skin_use, key=lambda k: (skin_use[k], -k))
    if len(skin_use) > 1:
        warn.append(f"file has {len(skin_use)} skins; kept skin {skin_index}, meshes on other skins left out")
    skin = r.get(gl.skins, skin_index, "skin")
    src_joints = list(skin.joints or [])
    if not src_joints:
        r.fail(f"skin {skin_index} has no joints")
    if len(set(src_joints)) != len(src_joints):
        r.fail(f"skin {skin_index} lists a joint twice")
    for j in src_joints:
        r.get(nodes, j, "joint node")
    joint_set = set(src_joints)

    def joint_parent(node: int):
        k = parent.get(node)
        while k is not None and k not in joint_set:
            k = parent.get(k)
        return k

    def between(node: int, ancestor) -> np.ndarray:
        """Product of node locals strictly between `ancestor` (a joint or None) and `node`."""
        m = np.eye(4)
        k = parent.get(node)
        while k is not None and k != ancestor:
            m = node_local_matrix(nodes[k]) @ m
            k = parent.get(k)
        return m

    # Parents-first order, stable in the skin's order.
    depth = {}
    for j in src_joints:
        d, k = 0, joint_parent(j)
        while k is not None:
            d, k = d + 1, joint_parent(k)
        depth[j] = d
    order = sorted(src_joints, key=lambda j: (depth[j], src_joints.index(j)))
    new_index = {node: i for i, node in enumerate(order)}
    skin_to_new = np.array([new_index[j] for j in src_joints], dtype=np.int64)
    jc = len(order)
    names = []
    for i, node in enumerate(order):
        name = nodes[node].name or f"joint{i}"
        names.append(name if name not in names else f"{name}.{i}")
    parents = np.array([new_index[joint_parent(n)] if joint_parent(n) is not None else -1 for n in order], dtype=np.int32)

    rest_t = np.zeros((jc, 3))
    rest_q = np.zeros((jc, 4))
    rest_s = np.zeros((jc, 3))
    folds: list[_Fold | None] = []
    for i, node in enumerate(order):
        t, q, s, shear = _node_trs(nodes[node])
        if shear > 1e-5:
            warn.append(f"joint {names[i]!r} matrix has shear {shear:.2g}; approximated by TRS")
        fold = _Fold(between(node, joint_parent(node)))
        if fold.identity:
            folds.append(None)
        else:
            if not fold.ok:
                r.fail(f"non-uniform scale or shear on a non-joint node above joint {names[i]!r} is not supported")
            t, q, s = fold.translation(t), fold.rotation(q), fold.scale(s)
            folds.append(fold)
        rest_t[i], rest_q[i], rest_s[i] = t, q, s

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

    if skin.inverseBindMatrices is not None:
        ibm_raw = r.accessor(skin.inverseBindMatrices, "inverseBindMatrices")
        if ibm_raw.shape != (len(src_joints), 16):
            r.fail(f"inverseBindMatrices has {ibm_raw.shape[0]} matrices for {len(src_joints)} joints")
        ibm_src = ibm_raw.astype(np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)
    else:
        ibm_src = np.tile(np.eye(4), (len(src_joints), 1, 1))
    ibm = np.empty((jc, 4, 4))
    ibm[skin_to_new] = ibm_src
    ibm = np.diag([factor, factor, factor, 1.0]) @ ibm
    if not np.all(np.isfinite(ibm)):
        r.fail("inverseBindMatrices hold NaN or Inf")

    skeleton = Skeleton(tuple(names), parents, rest_t, tf.quat_normalize(rest_q), rest_s, ibm).validate()

    meshes = _read_meshes(r, nodes, skin_index, skin_to_new, jc, warn)
    if not meshes:
        r.fail("the skinned meshes have no triangles")
    attachments, props = _read_rigid(r, nodes, parent, joint_set, new_index, factor, warn)
    sockets = {}
    for node, i in new_index.items():
        name = crowd_extras(nodes[node]).get("socket")
        if isinstance(name, str):
            sockets[name] = i
    clips = _read_clips(r, skeleton, new_index, folds, factor, joint_set, warn)
    name = Path(r.path).stem
    character = Character(name, skeleton, meshes, clips, attachments, props, sockets, warn)
    return character.validate()


def _attr(r: _Reader, prim, key: str):
    return getattr(prim.attributes, key, None)


def _indices(r: _Reader, prim, vertex_count: int, label: str) -> np.ndarray:
    if prim.indices is not None:
        idx = r.accessor(prim.indices, f"{label} indices")[:, 0].astype(np.int64)
    else:
        idx = np.arange(vertex_count, dtype=np.int64)
    idx = idx[: idx.shape[0] // 3 * 3]
    if idx.size and (idx.min() < 0 or idx.max() >= vertex_count):
        r.fail(f"{label} has an index past its {vertex_count} vertices")
    return idx


def _normals(r: _Reader, prim, pos: np.ndarray, idx: np.ndarray, label: str) -> np.ndarray:
    if _attr(r, prim, "NORMAL") is not None:
        return r.accessor(_attr(r, prim, "NORMAL"), f"{label} NORMAL").astype(np.float64)
    return vertex_normals(pos, idx)


def _base_color(r: _Reader, prim) -> tuple[tuple[float, ...], bool]:
    """(base colour factor, whether a base colour texture was left out)."""
    if prim.material is None:
        return (1.0, 1.0, 1.0, 1.0), False
    pbr = r.get(r.gltf.materials, prim.material, "material").pbrMetallicRoughness
    if pbr is None:
        return (1.0, 1.0, 1.0, 1.0), False
    base = tuple(float(x) for x in pbr.baseColorFactor) if pbr.baseColorFactor is not None else (1.0, 1.0, 1.0, 1.0)
    return base, pbr.baseColorTexture is not None


def _read_meshes(r: _Reader, nodes, skin_index: int, skin_to_new: np.ndarray, jc: int, warn: list[str]) -> list[SkinnedMesh]:
    gl = r.gltf
    meshes: list[SkinnedMesh] = []
    seen_mesh = set()
    textured = False
    for ni, node in enumerate(nodes):
        if node.mesh is None or node.skin != skin_index or node.mesh in seen_mesh:
            continue
        seen_mesh.add(node.mesh)
        mesh = r.get(gl.meshes, node.mesh, "mesh")
        extras = crowd_extras(mesh)
        for pi, prim in enumerate(mesh.primitives or []):
            label = mesh.name or f"mesh{node.mesh}"
            if len(mesh.primitives) > 1:
                label = f"{label}#{pi}"
            mode = 4 if prim.mode is None else prim.mode
            if mode != 4:
                warn.append(f"{label}: primitive mode {mode} is not triangles; left out")
                continue
            if prim.targets:
                warn.append(f"{label}: {len(prim.targets)} morph targets left out")
            if _attr(r, prim, "POSITION") is None:
                r.fail(f"{label} has no POSITION")
            pos = r.accessor(_attr(r, prim, "POSITION"), f"{label} POSITION").astype(np.float64)
            v = pos.shape[0]
            if _attr(r, prim, "JOINTS_0") is None or _attr(r, prim, "WEIGHTS_0") is None:
                r.fail(f"{label} is drawn with a skin but has no JOINTS_0/WEIGHTS_0")
            jsets, wsets = [], []
            k = 0
            while _attr(r, prim, f"JOINTS_{k}") is not None and _attr(r, prim, f"WEIGHTS_{k}") is not None:
                jj = r.accessor(_attr(r, prim, f"JOINTS_{k}"), f"{label} JOINTS_{k}")
                ww = r.accessor(_attr(r, prim, f"WEIGHTS_{k}"), f"{label} WEIGHTS_{k}").astype(np.float64)
                if jj.dtype.kind not in "u" or jj.shape != (v, 4) or ww.shape != (v, 4):
                    r.fail(f"{label} JOINTS_{k}/WEIGHTS_{k} must be unsigned VEC4 with one row per vertex")
                jsets.append(jj.astype(np.int64))
                wsets.append(ww)
                k += 1
            joints = np.concatenate(jsets, axis=1)
            weights = np.concatenate(wsets, axis=1)
            if not np.all(np.isfinite(weights)):
                r.fail(f"{label} WEIGHTS hold NaN or Inf")
            weights = np.maximum(weights, 0.0)
            used = weights > 0.0
            if np.any(joints[used] >= skin_to_new.shape[0]):
                r.fail(f"{label} references joint {int(joints[used].max())} but the skin has {skin_to_new.shape[0]}")
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
            idx = _indices(r, prim, v, label)
            nrm = _normals(r, prim, pos, idx, label)
            colors = _colors(r, prim, v, label)
            base, has_texture = _base_color(r, prim)
            textured |= has_texture
            if not np.all(np.isfinite(pos)):
                r.fail(f"{label} POSITION holds NaN or Inf")
            meshes.append(SkinnedMesh(
                name=label, piece=str(extras.get("piece", label)), lod=int(extras.get("lod", 0)),
                positions=pos.astype(np.float32), normals=tf.quat_normalize(np.concatenate([nrm, np.zeros((v, 1))], 1))[:, :3].astype(np.float32),
                joints=joints.astype(np.uint16), weights=weights.astype(np.float32), indices=idx.astype(np.uint32),
                colors=None if colors is None else colors.astype(np.float32), base_color=base, group=str(extras.get("group", "")),
            ))
    if textured:
        warn.append("textures left out: base colour factors and vertex colours are used")
    return meshes


def _colors(r: _Reader, prim, v: int, label: str) -> np.ndarray | None:
    """COLOR_0 as float64 RGBA (None when the primitive has none)."""
    if _attr(r, prim, "COLOR_0") is None:
        return None
    c = r.accessor(_attr(r, prim, "COLOR_0"), f"{label} COLOR_0").astype(np.float64)
    if c.shape != (v, 3) and c.shape != (v, 4):
        r.fail(f"{label} COLOR_0 must hold one RGB or RGBA colour per vertex, got shape {c.shape}")
    return np.concatenate([c, np.ones((v, 1))], axis=1) if c.shape[1] == 3 else c


def _rigid_mesh(r: _Reader, mesh_index: int, warn: list[str]) -> RigidMesh | None:
    mesh = r.get(r.gltf.meshes, mesh_index, "mesh")
    parts_p, parts_n, parts_i, parts_c, base = [], [], [], [], (1.0, 1.0, 1.0, 1.0)
    count = 0
    for prim in mesh.primitives or []:
        if (4 if prim.mode is None else prim.mode) != 4 or _attr(r, prim, "POSITION") is None:
            continue
        label = f"mesh {mesh.name or mesh_index!r}"
        pos = r.accessor(_attr(r, prim, "POSITION"), f"{label} POSITION").astype(np.float64)
        idx = _indices(r, prim, pos.shape[0], label)
        nrm = _normals(r, prim, pos, idx, label)
        base, _ = _base_color(r, prim)
        parts_c.append(_colors(r, prim, pos.shape[0], label))
        parts_p.append(pos)
        parts_n.append(nrm)
        parts_i.append(idx + count)
        count += pos.shape[0]
    if not parts_p:
        warn.append(f"mesh {mesh.name!r} has no triangles; left out")
        return None
    colors = None
    if any(c is not None for c in parts_c):  # primitives without colours are white
        colors = np.concatenate([np.ones((len(p), 4)) if c is None else c for p, c in zip(parts_p, parts_c)]).astype(np.float32)
    return RigidMesh(mesh.name or f"mesh{mesh_index}", np.concatenate(parts_p).astype(np.float32),
                     np.concatenate(parts_n).astype(np.float32), np.concatenate(parts_i).astype(np.uint32), colors, base)


def _read_rigid(r: _Reader, nodes, parent, joint_set, new_index, factor: float, warn: list[str]):
    attachments, props = [], {}
    for ni, node in enumerate(nodes):
        extras = crowd_extras(node)
        if node.mesh is not None and node.skin is None:
            if isinstance(extras.get("prop"), str):
                mesh = _rigid_mesh(r, node.mesh, warn)
                grip = np.eye(4)
                for c in node.children or []:
                    if crowd_extras(nodes[c]).get("grip") is not None:
                        grip = node_local_matrix(nodes[c])
                if mesh is not None:
                    props[extras["prop"]] = Prop(mesh, grip)
                continue
            # Walk up to the nearest joint, collecting the offset from it.
            offset, k = node_local_matrix(node), parent.get(ni)
            while k is not None and k not in joint_set:
                offset = node_local_matrix(nodes[k]) @ offset
                k = parent.get(k)
            if k is None:
                warn.append(f"static mesh {node.name or ni!r} is not skinned nor under a joint; left out")
                continue
            mesh = _rigid_mesh(r, node.mesh, warn)
            if mesh is not None:
                attachments.append(Attachment(mesh, new_index[k], np.diag([factor, factor, factor, 1.0]) @ offset))
    return attachments, props


def _read_clips(r: _Reader, skeleton: Skeleton, new_index, folds, factor: float, joint_set, warn: list[str]) -> list[Clip]:
    gl = r.gltf
    anims = gl.animations or []
    targets = [{ch.target.node for ch in (a.channels or []) if ch.target is not None} for a in anims]
    # Old exporters wrote one animation per joint; a set of single-node animations with disjoint
    # targets is one clip split up, so it is merged back.
    merge = len(anims) > 1 and all(len(t) == 1 for t in targets) and len(set().union(*targets)) == len(anims)
    groups = [(Path(r.path).stem, list(range(len(anims))))] if merge else [(a.name or f"clip{i}", [i]) for i, a in enumerate(anims)]
    if merge:
        warn.append(f"merged {len(anims)} single-joint animations (old one-animation-per-joint layout) into one clip")
    clips: list[Clip] = []
    for name, members in groups:
        channels: dict[tuple[int, str], Channel] = {}
        extras = crowd_extras(anims[members[0]])
        for ai in members:
            anim = anims[ai]
            for ci, ch in enumerate(anim.channels or []):
                where = f"animation {anim.name or ai!r} channel {ci}"
                if ch.target is None or ch.target.node is None:
                    continue
                if ch.target.path == "weights":
                    warn.append(f"{where}: morph weight animation left out")
                    continue
                if ch.target.node not in joint_set:
                    warn.append(f"{where}: animates non-joint node {ch.target.node}; left out")
                    continue
                sampler = r.get(anim.samplers, ch.sampler, f"{where} sampler")
                interp = sampler.interpolation or "LINEAR"
                if interp not in ("LINEAR", "STEP", "CUBICSPLINE"):
                    r.fail(f"{where}: unknown interpolation {interp!r}")
                times = r.accessor(sampler.input, f"{where} input")[:, 0].astype(np.float64)
                values = r.accessor(sampler.output, f"{where} output").astype(np.float64)
                if not np.all(np.isfinite(times)) or not np.all(np.isfinite(values)):
                    r.fail(f"{where} holds NaN or Inf")
                k = times.shape[0]
                if k == 0:
                    warn.append(f"{where}: no keys; left out")
                    continue
                if k > 1 and np.any(np.diff(times) <= 0):
                    r.fail(f"{where}: key times do not increase")
                comps = 4 if ch.target.path == "rotation" else 3
                if values.shape[1] != comps:
                    r.fail(f"{where}: {ch.target.path} output has {values.shape[1]} components")
                want = 3 * k if interp == "CUBICSPLINE" else k
                if values.shape[0] != want:
                    r.fail(f"{where}: {values.shape[0]} output values for {k} keys ({interp})")
                if interp == "CUBICSPLINE":
                    values = values.reshape(k, 3, comps)
                j = new_index[ch.target.node]
                values = _convert_keys(ch.target.path, values, interp, folds[j], factor, skeleton.parents[j] < 0)
                key = (j, ch.target.path)
                if key in channels:
                    warn.append(f"{where}: second {ch.target.path} channel for joint {skeleton.names[j]!r}; left out")
                    continue
                channels[key] = Channel(j, ch.target.path, interp, times, values)
        if not channels:
            warn.append(f"animation {name!r} animates no joint of the skin; left out")
            continue
        chans = sorted(channels.values(), key=lambda c: (c.joint, c.path))
        start = min(float(c.times[0]) for c in chans)
        end = max(float(c.times[-1]) for c in chans)
        clip = Clip(name, chans, start, end, False, {}, None)
        loop = extras.get("loop")
        clip.loop = bool(loop) if isinstance(loop, bool) else _looks_looped(skeleton, clip)
        markers = extras.get("markers")
        if isinstance(markers, dict):
            clip.markers = {str(k): float(v) for k, v in markers.items()}
        if isinstance(extras.get("stride"), (int, float)):
            clip.stride = float(extras["stride"])
        base, n = clip.name, 1
        while any(c.name == clip.name for c in clips):
            n += 1
            clip.name = f"{base}.{n}"
        clips.append(clip)
    return clips


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
