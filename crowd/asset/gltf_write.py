"""Write a Character as a binary glTF 2.0 file (pygltflib builds the container).

Layout, chosen so a standard viewer shows something sensible and the importer recovers everything:
- node 0 is the armature (a non-joint parent of the root joint), nodes 1..J are the joints;
- one skin; one mesh per (piece, LOD), each drawn by its own node;
- scene 0 shows LOD0 with the first piece of each variation group; scenes "lod1", "lod2" show the
  lower LODs; scene "variants" holds the other variation pieces; scene "props" holds the props, each
  with a child ``<name>_grip`` node for its grip frame; scene "prop_lods" holds their coarser meshes
  (``extras.crowd`` prop and lod, in the prop's space);
- base-colour textures as PNG images in the binary chunk, each with its sampler; a textured mesh has
  a material of its own (its base colour factor and texture) and TEXCOORD_0;
- project-specific facts (piece, LOD, group, loop flag, phase markers, stride, socket, prop) live in
  ``extras.crowd``, which viewers ignore;
- morph targets as each primitive's ``targets`` (POSITION and NORMAL deltas), named in the mesh's
  ``extras.targetNames`` (the exporters' convention), with its default ``weights``; a target's deltas are
  written sparse (glTF 2.0 3.6.2.3: the vertices it moves, and their deltas) where that is smaller than
  dense, or as the caller says; a clip's morph weights as one ``weights`` channel per mesh node whose
  targets it drives, in that mesh's target order (glTF animates all of a node's weights at once).
Every write goes through a temporary file and an atomic rename.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pygltflib as g

from .model import Character, Clip, ModelError, MorphChannel, SkinnedMesh
from ..files import atomic_write_bytes
from ..transforms import mat4_decompose

FLOAT, UBYTE, USHORT, UINT = 5126, 5121, 5123, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963


class _Blob:
    def __init__(self, gltf: g.GLTF2):
        self.gltf = gltf
        self.data = bytearray()
        self._dedupe: dict[bytes, int] = {}

    def view(self, raw: bytes, target=None) -> int:
        """A bufferView of `raw`, 4-byte aligned in the binary chunk."""
        while len(self.data) % 4:
            self.data.append(0)
        self.gltf.bufferViews.append(g.BufferView(buffer=0, byteOffset=len(self.data), byteLength=len(raw), target=target))
        self.data += raw
        return len(self.gltf.bufferViews) - 1

    def accessor(self, array: np.ndarray, component: int, kind: str, target=None, normalized=False, minmax=False, dedupe=False) -> int:
        raw = np.ascontiguousarray(array).tobytes()
        key = raw + kind.encode() + bytes([component % 256])
        if dedupe and key in self._dedupe:
            return self._dedupe[key]
        count = array.shape[0]
        acc = g.Accessor(bufferView=self.view(raw, target), componentType=component, count=count, type=kind,
                         normalized=True if normalized else None)
        if minmax:
            flat = array.reshape(count, -1)
            acc.min = [float(x) for x in flat.min(axis=0)]
            acc.max = [float(x) for x in flat.max(axis=0)]
        self.gltf.accessors.append(acc)
        index = len(self.gltf.accessors) - 1
        if dedupe:
            self._dedupe[key] = index
        return index

    def sparse_accessor(self, array: np.ndarray, kind: str) -> int:
        """A float accessor of `array` (count, C) written as its rows that are not zero, over zeros (no
        bufferView); all zeros needs no sparse part at all."""
        count = array.shape[0]
        moved = np.flatnonzero(np.any(array != 0, axis=1))
        acc = g.Accessor(componentType=FLOAT, count=count, type=kind, byteOffset=None,
                         min=[float(x) for x in array.min(axis=0)], max=[float(x) for x in array.max(axis=0)])
        if moved.size:
            wide = count > 65535
            indices = self.view(moved.astype(np.uint32 if wide else np.uint16).tobytes())
            values = self.view(np.ascontiguousarray(array[moved], np.float32).tobytes())
            acc.sparse = g.Sparse(count=int(moved.size), indices=g.AccessorSparseIndices(bufferView=indices, componentType=UINT if wide else USHORT),
                                  values=g.AccessorSparseValues(bufferView=values))
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1


def _trs_fields(t: np.ndarray, q: np.ndarray, s: np.ndarray) -> dict:
    """Node TRS fields, leaving out those at their defaults."""
    out = {}
    if np.any(np.abs(t) > 0):
        out["translation"] = [float(x) for x in np.float32(t)]
    if np.any(np.abs(q - [0, 0, 0, 1]) > 0):
        out["rotation"] = [float(x) for x in np.float32(q)]
    if np.any(np.abs(s - 1) > 1e-9):
        out["scale"] = [float(x) for x in np.float32(s)]
    return out


def _targets(blob: _Blob, mesh: SkinnedMesh, sparse: bool | None) -> list[g.Attributes]:
    """The mesh's morph targets: POSITION (with the min and max glTF asks of it) and NORMAL deltas."""
    out = []
    for positions, normals in zip(mesh.morph_positions, mesh.morph_normals):
        moved = int(np.count_nonzero(np.any(positions != 0, axis=1) | np.any(normals != 0, axis=1)))
        # Sparse costs an index (2 or 4 bytes) and a delta (12) per moved vertex against 12 a vertex dense.
        if sparse if sparse is not None else moved * (14 if len(positions) <= 65535 else 16) < 12 * len(positions):
            out.append(g.Attributes(POSITION=blob.sparse_accessor(positions, "VEC3"), NORMAL=blob.sparse_accessor(normals, "VEC3")))
        else:
            out.append(g.Attributes(POSITION=blob.accessor(np.ascontiguousarray(positions, np.float32), FLOAT, "VEC3", ARRAY_BUFFER, minmax=True),
                                    NORMAL=blob.accessor(np.ascontiguousarray(normals, np.float32), FLOAT, "VEC3", ARRAY_BUFFER)))
    return out


def _primitive(blob: _Blob, mesh, joint_count: int | None, material: int, sparse: bool | None = None) -> g.Primitive:
    attrs = g.Attributes(
        POSITION=blob.accessor(mesh.positions.astype(np.float32), FLOAT, "VEC3", ARRAY_BUFFER, minmax=True),
        NORMAL=blob.accessor(mesh.normals.astype(np.float32), FLOAT, "VEC3", ARRAY_BUFFER),
    )
    if mesh.colors is not None:
        col = np.round(np.clip(mesh.colors, 0, 1) * 255.0).astype(np.uint8)
        attrs.COLOR_0 = blob.accessor(col, UBYTE, "VEC4", ARRAY_BUFFER, normalized=True)
    if mesh.texture >= 0:
        attrs.TEXCOORD_0 = blob.accessor(np.asarray(mesh.uvs, np.float32), FLOAT, "VEC2", ARRAY_BUFFER)
    if isinstance(mesh, SkinnedMesh):
        small = joint_count <= 256
        attrs.JOINTS_0 = blob.accessor(mesh.joints.astype(np.uint8 if small else np.uint16), UBYTE if small else USHORT, "VEC4", ARRAY_BUFFER)
        attrs.WEIGHTS_0 = blob.accessor(mesh.weights.astype(np.float32), FLOAT, "VEC4", ARRAY_BUFFER)
    wide = mesh.positions.shape[0] > 65535
    idx = mesh.indices.astype(np.uint32 if wide else np.uint16)
    targets = _targets(blob, mesh, sparse) if isinstance(mesh, SkinnedMesh) and mesh.morph_count else []
    return g.Primitive(attributes=attrs, indices=blob.accessor(idx, UINT if wide else USHORT, "SCALAR", ELEMENT_ARRAY_BUFFER),
                       material=material, mode=4, targets=targets)


def _weights_channel(clip: Clip, targets: np.ndarray) -> MorphChannel | None:
    """The weights of a mesh's `targets` (character morph indices, in the mesh's order) over `clip`, as one
    channel, or None when the clip drives none of them. The clip's channels that drive them must share
    key times and interpolation (as a glTF file's do: it drives each node's weights with one); targets
    none of them drives hold their default weight, which the caller fills in (NaN here)."""
    used = [ch for ch in clip.morph_channels if np.isin(ch.morphs, targets).any()]
    if not used:
        return None
    first = used[0]
    if any(ch.interpolation != first.interpolation or not np.array_equal(ch.times, first.times) for ch in used[1:]):
        raise ModelError(f"clip {clip.name!r}: the morph channels of one mesh have different key times or interpolations; "
                         "glTF animates a mesh's weights with one channel")
    cubic = first.interpolation == "CUBICSPLINE"
    values = np.full(first.values.shape[:-1] + (len(targets),), np.nan)
    for ch in used:
        for column, morph in enumerate(ch.morphs):
            where = np.flatnonzero(targets == morph)
            if where.size:
                values[..., where[0]] = ch.values[..., column]
    if cubic:  # an undriven target holds still: zero tangents
        values[:, 0::2][np.isnan(values[:, 0::2])] = 0.0
    return MorphChannel(targets, first.interpolation, first.times, values)


def _png(pixels: np.ndarray) -> bytes:
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(pixels), mode="RGBA").save(out, format="PNG")
    return out.getvalue()


def _textures(blob: _Blob, character: Character) -> None:
    """glTF textures 0..T-1 for the character's textures (an image each distinct pixels array)."""
    gl = blob.gltf
    images: dict[int, int] = {}
    for tex in character.textures:
        if id(tex.pixels) not in images:
            gl.images.append(g.Image(name=tex.name, mimeType="image/png", bufferView=blob.view(_png(tex.pixels))))
            images[id(tex.pixels)] = len(gl.images) - 1
        gl.samplers.append(g.Sampler(magFilter=tex.mag_filter, minFilter=tex.min_filter, wrapS=tex.wrap[0], wrapT=tex.wrap[1]))
        gl.textures.append(g.Texture(source=images[id(tex.pixels)], sampler=len(gl.samplers) - 1))


def _material(gl: g.GLTF2, mesh, untextured: int) -> int:
    """White untextured meshes share material `untextured`; a textured or tinted one gets its own."""
    if mesh.texture < 0 and tuple(mesh.base_color) == (1.0, 1.0, 1.0, 1.0):
        return untextured
    texture = g.TextureInfo(index=mesh.texture) if mesh.texture >= 0 else None
    gl.materials.append(g.Material(name=f"{mesh.name}_material", pbrMetallicRoughness=g.PbrMetallicRoughness(
        baseColorFactor=[float(x) for x in mesh.base_color], baseColorTexture=texture, metallicFactor=0.0, roughnessFactor=0.9)))
    return len(gl.materials) - 1


def character_to_gltf(character: Character, sparse: bool | None = None) -> tuple[g.GLTF2, bytes]:
    """The glTF document and binary chunk of `character`; `sparse` writes every morph target sparse
    (True) or dense (False) instead of whichever is smaller (None)."""
    character.validate()
    sk = character.skeleton
    gl = g.GLTF2(asset=g.Asset(version="2.0", generator="crowd gltf_write"))
    blob = _Blob(gl)
    gl.materials.append(g.Material(name="zombie", pbrMetallicRoughness=g.PbrMetallicRoughness(
        baseColorFactor=[1.0, 1.0, 1.0, 1.0], metallicFactor=0.0, roughnessFactor=0.9)))
    gl.materials.append(g.Material(name="prop", pbrMetallicRoughness=g.PbrMetallicRoughness(
        baseColorFactor=[1.0, 1.0, 1.0, 1.0], metallicFactor=0.6, roughnessFactor=0.5)))
    _textures(blob, character)

    socket_names = {j: name for name, j in character.sockets.items()}
    gl.nodes.append(g.Node(name=character.name, children=[1 + j for j in range(sk.joint_count) if sk.parents[j] < 0]))
    for j in range(sk.joint_count):
        node = g.Node(name=sk.names[j], children=[1 + c for c in range(sk.joint_count) if sk.parents[c] == j],
                      **_trs_fields(sk.rest_translation[j], sk.rest_rotation[j], sk.rest_scale[j]))
        if j in socket_names:
            node.extras = {"crowd": {"socket": socket_names[j]}}
        gl.nodes.append(node)
    ibm = np.ascontiguousarray(np.transpose(sk.inverse_bind, (0, 2, 1))).astype(np.float32)  # glTF is column-major
    gl.skins.append(g.Skin(name=f"{character.name}_skin", joints=list(range(1, 1 + sk.joint_count)), skeleton=1,
                           inverseBindMatrices=blob.accessor(ibm, FLOAT, "MAT4")))

    scenes: dict[str, list[int]] = {}
    seen_groups: dict[tuple[int, str], str] = {}
    morph_nodes: list[tuple[int, SkinnedMesh]] = []
    for mesh in character.meshes:
        extras = {"crowd": {"piece": mesh.piece, "lod": mesh.lod, "group": mesh.group}}
        weights = []
        if mesh.morph_count:
            extras["targetNames"] = [character.morphs[t] for t in mesh.morph_targets]
            weights = [float(character.morph_defaults[t]) for t in mesh.morph_targets]
        gl.meshes.append(g.Mesh(name=mesh.name, primitives=[_primitive(blob, mesh, sk.joint_count, _material(gl, mesh, 0), sparse)],
                                extras=extras, weights=weights))
        gl.nodes.append(g.Node(name=mesh.name, mesh=len(gl.meshes) - 1, skin=0))
        if mesh.morph_count:
            morph_nodes.append((len(gl.nodes) - 1, mesh))
        first = not mesh.group or seen_groups.setdefault((mesh.lod, mesh.group), mesh.piece) == mesh.piece
        scene = ("zombie" if mesh.lod == 0 else f"lod{mesh.lod}") if first else "variants"
        scenes.setdefault(scene, [0]).append(len(gl.nodes) - 1)

    props = []
    for name, prop in character.props.items():
        gl.meshes.append(g.Mesh(name=prop.mesh.name, primitives=[_primitive(blob, prop.mesh, None, _material(gl, prop.mesh, 1))]))
        gl.nodes.append(g.Node(name=prop.mesh.name, mesh=len(gl.meshes) - 1, extras={"crowd": {"prop": name}},
                               children=[len(gl.nodes) + 1]))
        props.append(len(gl.nodes) - 1)
        gl.nodes.append(g.Node(name=f"{prop.mesh.name}_grip", extras={"crowd": {"grip": name}}, **_trs_fields(*mat4_decompose(prop.grip)[:3])))
        for lod, coarse in enumerate(prop.coarser, start=1):  # in the prop's space, placed through its grip
            gl.meshes.append(g.Mesh(name=coarse.name, primitives=[_primitive(blob, coarse, None, _material(gl, coarse, 1))]))
            gl.nodes.append(g.Node(name=coarse.name, mesh=len(gl.meshes) - 1, extras={"crowd": {"prop": name, "lod": lod}}))
            scenes.setdefault("prop_lods", []).append(len(gl.nodes) - 1)
    if props:
        scenes["props"] = props

    for clip in character.clips:
        anim = g.Animation(name=clip.name, extras={"crowd": {"loop": clip.loop, "markers": clip.markers, "stride": clip.stride}})
        for ch in clip.channels:
            times = blob.accessor(ch.times.astype(np.float32), FLOAT, "SCALAR", minmax=True, dedupe=True)
            vals = ch.values.reshape(-1, ch.values.shape[-1]).astype(np.float32)
            out = blob.accessor(vals, FLOAT, "VEC4" if ch.path == "rotation" else "VEC3")
            anim.samplers.append(g.AnimationSampler(input=times, output=out, interpolation=ch.interpolation))
            anim.channels.append(g.AnimationChannel(sampler=len(anim.samplers) - 1,
                                                    target=g.AnimationChannelTarget(node=1 + ch.joint, path=ch.path)))
        for node, mesh in morph_nodes:
            ch = _weights_channel(clip, mesh.morph_targets)
            if ch is None:
                continue
            values = ch.values.copy()
            undriven = np.isnan(values)
            values[undriven] = np.broadcast_to(character.morph_defaults[mesh.morph_targets], values.shape)[undriven]
            times = blob.accessor(ch.times.astype(np.float32), FLOAT, "SCALAR", minmax=True, dedupe=True)
            out = blob.accessor(values.reshape(-1, 1).astype(np.float32), FLOAT, "SCALAR")
            anim.samplers.append(g.AnimationSampler(input=times, output=out, interpolation=ch.interpolation))
            anim.channels.append(g.AnimationChannel(sampler=len(anim.samplers) - 1, target=g.AnimationChannelTarget(node=node, path="weights")))
        gl.animations.append(anim)

    order = ["zombie"] + sorted(k for k in scenes if k.startswith("lod")) + ["variants", "props", "prop_lods"]
    for name in order:
        if name in scenes:
            gl.scenes.append(g.Scene(name=name, nodes=scenes[name]))
    gl.scene = 0
    gl.buffers.append(g.Buffer(byteLength=len(blob.data)))
    return gl, bytes(blob.data)


def glb_bytes(character: Character, sparse: bool | None = None) -> bytes:
    gl, data = character_to_gltf(character, sparse)
    gl.set_binary_blob(data)
    return b"".join(gl.save_to_bytes())


def write_glb(character: Character, path: Path, sparse: bool | None = None) -> int:
    data = glb_bytes(character, sparse)
    atomic_write_bytes(Path(path), data)
    return len(data)

