"""Meshes: each triangle primitive drawn with a merged skin becomes a ``SkinnedMesh`` (its piece, LOD
and variation group from ``extras.crowd``), with its morph targets; rigid meshes under a joint become
attachments, and meshes marked ``extras.crowd.prop`` the props the crowd holds.

Morph targets. Each skinned primitive's ``targets`` (POSITION and NORMAL deltas; sparse or dense, float
or KHR_mesh_quantization integers) become the mesh's ``morph_positions`` / ``morph_normals``; targets are
the character's by name (``extras.targetNames``, else "<mesh>.target<k>"), so a mesh's LODs and
primitives share theirs; default weights come from the mesh, overridden by the node drawing it (a
``weights`` channel is read with the clips: crowd.asset.gltf.clips).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ... import transforms as tf
from ..model import MAX_MORPHS, Attachment, Prop, RigidMesh, SkinnedMesh, vertex_normals
from .draco import decode_primitive
from .materials import Materials
from .reader import (MAX_COORDINATE, MAX_MORPH_WEIGHT, UNSIGNED_TYPES, Reader, check_matrices, crowd_extras, first_row, is_whole,
                     refuse_bad_values, show)
from .tree import Tree

WEIGHT_NOISE = 1e-6  # float exporters leave -1e-8 where they mean 0
MAX_LOD = 15


def _attr(r: Reader, prim: dict, key: str, label: str):
    attributes = r.obj(prim, "attributes", label) or {}
    return r.index(attributes, key, "accessors", f"{label} attribute")


def _vertex_data(r: Reader, prim: dict, key: str, label: str, v: int, types, components=None) -> np.ndarray | None:
    """An attribute with one row per vertex, or None when the primitive has none."""
    index = _attr(r, prim, key, label)
    if index is None:
        return None
    data = r.accessor(index, f"{label} {key}", types, components)
    if data.shape[0] != v:
        r.fail(f"accessor {index} ({label} {key}) has {data.shape[0]} elements for {v} vertices")
    return data


def _positions(r: Reader, prim: dict, label: str) -> np.ndarray:
    index = _attr(r, prim, "POSITION", label)
    acc = r.item("accessors", index)
    if acc.get("bufferView") is None and acc.get("sparse") is None and index not in r.decoded:
        r.fail(f"accessor {index} ({label} POSITION) has no data (no bufferView: compressed by an extension?)")
    what = f"accessor {index} ({label} POSITION)"
    pos = r.accessor(index, f"{label} POSITION", ("VEC3",)).astype(np.float64)
    refuse_bad_values(r, pos, what, "vertex", MAX_COORDINATE)
    return pos


def _indices(r: Reader, prim: dict, vertex_count: int, label: str, warn: list[str]) -> np.ndarray:
    index = r.index(prim, "indices", "accessors", label)
    if index is not None:
        idx = r.accessor(index, f"{label} indices", ("SCALAR",), UNSIGNED_TYPES)[:, 0].astype(np.int64)
    else:
        idx = np.arange(vertex_count, dtype=np.int64)
    if idx.shape[0] % 3:
        warn.append(f"{label}: {idx.shape[0]} indices are not whole triangles; the last {idx.shape[0] % 3} left out")
    idx = idx[: idx.shape[0] // 3 * 3]
    if idx.size and idx.max() >= vertex_count:
        k = int(np.argmax(idx >= vertex_count))
        r.fail(f"{label} has an index past its {vertex_count} vertices (index {k} is {int(idx[k])})")
    return idx


def _normals(r: Reader, prim: dict, pos: np.ndarray, idx: np.ndarray, label: str, warn: list[str]) -> np.ndarray:
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


def _colors(r: Reader, prim: dict, v: int, label: str) -> np.ndarray | None:
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
        r.fail(f"{what}: vertex {first_row(bad)} has a NaN or infinite colour")
    return np.concatenate([c, np.ones((v, 1))], axis=1) if c.shape[1] == 3 else c


def _uvs(r: Reader, prim: dict, surface, materials: Materials, label: str, v: int) -> np.ndarray | None:
    """The texture coordinates of a textured surface (None: untextured, or it has none)."""
    if surface.texture < 0:
        return None
    key = f"TEXCOORD_{surface.texcoord}"
    raw = _vertex_data(r, prim, key, label, v, ("VEC2",))
    return materials.uvs(surface, raw, label, f"accessor {_attr(r, prim, key, label)} ({label} {key})")


def _mode(r: Reader, prim: dict, label: str) -> int:
    return r.whole(prim, "mode", label, default=4, hi=6)


def _mesh_extras(r: Reader, extras: dict, label: str) -> tuple[str, int, str]:
    """(piece, lod, group) from a mesh's extras.crowd."""
    lod = extras.get("lod", 0)
    if isinstance(lod, float) and lod.is_integer():
        lod = int(lod)
    if not is_whole(lod) or not 0 <= lod <= MAX_LOD:
        r.fail(f"{label}: extras.crowd.lod must be a whole number from 0 to {MAX_LOD}, got {show(lod)}")
    return str(extras.get("piece", label)), lod, str(extras.get("group", ""))


class Morphs:
    """The character's morph targets, gathered from its skinned meshes: one per target name (a mesh's
    targets, its other primitives' and its LODs' share a name), with the default weight of the first
    mesh that has it. glTF names targets in mesh.extras.targetNames (the exporters' convention, Blender's
    among them); unnamed ones are named after their mesh and number, so they are never merged by accident."""

    def __init__(self, r: Reader, warn: list[str]):
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
            r.fail(f"{where}: default weight {first_row(big)} is {float(defaults[big][0]):.6g}, beyond ±{MAX_MORPH_WEIGHT:g}")
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


def _target_deltas(r: Reader, target, key: str, k: int, v: int, label: str) -> np.ndarray | None:
    """Target k's per-vertex differences of `key` (POSITION or NORMAL), float64 (V, 3), or None."""
    index = r.index(target, key, "accessors", f"{label} target {k}")
    if index is None:
        return None
    what = f"accessor {index} ({label} target {k} {key})"
    # glTF and KHR_mesh_quantization: float, or (normalised or not) signed bytes and shorts.
    d = r.accessor(index, f"{label} target {k} {key}", ("VEC3",), (5126, 5120, 5122)).astype(np.float64)
    if d.shape[0] != v:
        r.fail(f"{what} has {d.shape[0]} elements for {v} vertices")
    refuse_bad_values(r, d, what, "vertex", MAX_COORDINATE, "moves beyond ±{limit:g}")
    return d


def _read_targets(r: Reader, morphs: Morphs, mesh_index: int, mesh: dict, node: dict, prim: dict, primitives: list,
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


def _joints_and_weights(r: Reader, prim: dict, label: str, v: int, skin_to_new: np.ndarray, warn: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """A skinned primitive's four influences a vertex (the skeleton's joints, weights summing to 1), from
    its JOINTS_n and WEIGHTS_n sets."""
    if _attr(r, prim, "JOINTS_0", label) is None or _attr(r, prim, "WEIGHTS_0", label) is None:
        r.fail(f"{label} is drawn with a skin but has no JOINTS_0/WEIGHTS_0")
    jsets, wsets = [], []
    k = 0
    while _attr(r, prim, f"JOINTS_{k}", label) is not None and _attr(r, prim, f"WEIGHTS_{k}", label) is not None:
        jj = _vertex_data(r, prim, f"JOINTS_{k}", label, v, ("VEC4",), UNSIGNED_TYPES)
        ww = _vertex_data(r, prim, f"WEIGHTS_{k}", label, v, ("VEC4",), (5126, 5121, 5123)).astype(np.float64)
        what = f"accessor {_attr(r, prim, f'WEIGHTS_{k}', label)} ({label} WEIGHTS_{k})"
        bad = ~np.isfinite(ww)
        if np.any(bad):
            r.fail(f"{what}: vertex {first_row(bad)} has a NaN or infinite weight")
        negative = ww < -WEIGHT_NOISE
        if np.any(negative):
            r.fail(f"{what}: vertex {first_row(negative)} has a negative weight ({float(ww[negative][0]):.3g})")
        jsets.append(jj.astype(np.int64))
        wsets.append(ww)
        k += 1
    joints = np.concatenate(jsets, axis=1)
    weights = np.concatenate(wsets, axis=1)
    weights = np.maximum(weights, 0.0)
    used = weights > 0.0
    if np.any(joints[used] >= skin_to_new.shape[0]):
        vertex = first_row(used & (joints >= skin_to_new.shape[0]))
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
    return joints, weights


def _on_node(v: int, joint: int) -> tuple[np.ndarray, np.ndarray]:
    """`v` vertices weighted wholly to `joint`."""
    joints = np.zeros((v, 4), np.int64)
    joints[:, 0] = joint
    weights = np.zeros((v, 4))
    weights[:, 0] = 1.0
    return joints, weights


def read_meshes(r: Reader, tree: Tree, skin_maps: dict[int, np.ndarray], materials: Materials, morphs: Morphs,
                 warn: list[str], node_joints: dict[int, int] | None = None) -> list[SkinnedMesh]:
    """The meshes drawn with the merged skins; `skin_maps[k]` maps skin k's joint indices to the skeleton's.
    `node_joints` (crowd.asset.gltf.skins.skin_of_nodes): a file without a skin, each mesh weighted wholly
    to its node's joint in the skin made of them (any JOINTS_n and WEIGHTS_n it holds mean nothing then)."""
    meshes: list[SkinnedMesh] = []
    seen_mesh: set[tuple[int, int]] = set()
    read_mesh: set[int] = set()
    for node_index, node in enumerate(tree.nodes):
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
            decode_primitive(r, prim, label)
            pos = _positions(r, prim, label)
            v = pos.shape[0]
            if node_joints is not None:
                joints, weights = _on_node(v, int(skin_to_new[node_joints[node_index]]))
            else:
                joints, weights = _joints_and_weights(r, prim, label, v, skin_to_new, warn)
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
                morph_targets=morph_targets, morph_positions=morph_positions, morph_normals=morph_normals, unlit=surface.unlit,
            ))
    return meshes


def _rigid_parts(r: Reader, mesh_index: int, materials: Materials, warn: list[str], textures: bool = True) -> list[RigidMesh]:
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
        decode_primitive(r, prim, label)
        pos = _positions(r, prim, label)
        idx = _indices(r, prim, pos.shape[0], label, warn)
        if not idx.size:
            continue
        nrm = _normals(r, prim, pos, idx, label, warn)
        surface = materials.surface(prim, label, textures)
        uvs = _uvs(r, prim, surface, materials, label, pos.shape[0])
        colors = _colors(r, prim, pos.shape[0], label)
        colors = (np.ones((pos.shape[0], 4)) if colors is None else colors) * np.asarray(surface.base_color)
        parts.setdefault((surface.texture if uvs is not None else -1, surface.unlit), []).append((pos, nrm, idx, colors, uvs))
    if not parts:
        warn.append(f"mesh {mesh_name!r} has no triangles; left out")
        return []
    out = []
    for (texture, unlit), prims in sorted(parts.items()):
        starts = np.cumsum([0] + [len(p[0]) for p in prims])
        name = mesh_name or f"mesh{mesh_index}"
        out.append(RigidMesh(
            name if len(parts) == 1 else f"{name}#{len(out)}",
            np.concatenate([p[0] for p in prims]).astype(np.float32), np.concatenate([p[1] for p in prims]).astype(np.float32),
            np.concatenate([p[2] + k for p, k in zip(prims, starts)]).astype(np.uint32),
            np.concatenate([p[3] for p in prims]).astype(np.float32), texture=texture,
            uvs=np.concatenate([p[4] for p in prims]).astype(np.float32) if texture >= 0 else None, unlit=unlit))
    return out


def _untextured(parts: list[RigidMesh], label: str, warn: list[str]) -> RigidMesh | None:
    """The parts as one untextured mesh (a prop: the weapons stage draws one mesh per prop), unlit where
    every part is (KHR_materials_unlit)."""
    if not parts:
        return None
    unlit = all(p.unlit for p in parts)
    mixed = f"{label}: some of its materials are unlit and some lit; drawn lit"
    if any(p.unlit for p in parts) and not unlit and mixed not in warn:  # (once, not once per LOD)
        warn.append(mixed)
    starts = np.cumsum([0] + [len(p.positions) for p in parts])
    return RigidMesh(parts[0].name.split("#")[0], np.concatenate([p.positions for p in parts]), np.concatenate([p.normals for p in parts]),
                     np.concatenate([p.indices + k for p, k in zip(parts, starts)]).astype(np.uint32), np.concatenate([p.colors for p in parts]),
                     unlit=unlit)


def read_rigid(r: Reader, tree: Tree, new_index, factor: float, materials: Materials, warn: list[str]):
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
                mesh = _untextured(parts, f"prop {extras['prop']!r}", warn)
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
                        check_matrices(r, grip[None], f"{r.node_where(c)} (grip of prop {extras['prop']!r})")
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
        if len({m.unlit for m in lods}) > 1:
            warn.append(f"prop {name!r}: its LODs differ in KHR_materials_unlit; each is drawn as its own material says")
    return attachments, props

