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
  ``extras.crowd``, which viewers ignore.
Every write goes through a temporary file and an atomic rename.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pygltflib as g

from .model import Character, SkinnedMesh
from ..files import atomic_write_bytes
from ..transforms import mat4_decompose

FLOAT, UBYTE, USHORT, UINT = 5126, 5121, 5123, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963


class _Blob:
    def __init__(self, gltf: g.GLTF2):
        self.gltf = gltf
        self.data = bytearray()
        self._dedupe: dict[bytes, int] = {}

    def accessor(self, array: np.ndarray, component: int, kind: str, target=None, normalized=False, minmax=False, dedupe=False) -> int:
        raw = np.ascontiguousarray(array).tobytes()
        key = raw + kind.encode() + bytes([component % 256])
        if dedupe and key in self._dedupe:
            return self._dedupe[key]
        while len(self.data) % 4:
            self.data.append(0)
        view = g.BufferView(buffer=0, byteOffset=len(self.data), byteLength=len(raw), target=target)
        self.data += raw
        self.gltf.bufferViews.append(view)
        count = array.shape[0]
        acc = g.Accessor(bufferView=len(self.gltf.bufferViews) - 1, componentType=component, count=count, type=kind,
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


def _primitive(blob: _Blob, mesh, joint_count: int | None, material: int) -> g.Primitive:
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
    return g.Primitive(attributes=attrs, indices=blob.accessor(idx, UINT if wide else USHORT, "SCALAR", ELEMENT_ARRAY_BUFFER),
                       material=material, mode=4)


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
            data = _png(tex.pixels)
            while len(blob.data) % 4:
                blob.data.append(0)
            gl.bufferViews.append(g.BufferView(buffer=0, byteOffset=len(blob.data), byteLength=len(data)))
            blob.data += data
            gl.images.append(g.Image(name=tex.name, mimeType="image/png", bufferView=len(gl.bufferViews) - 1))
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


def character_to_gltf(character: Character) -> tuple[g.GLTF2, bytes]:
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
    for mesh in character.meshes:
        gl.meshes.append(g.Mesh(name=mesh.name, primitives=[_primitive(blob, mesh, sk.joint_count, _material(gl, mesh, 0))],
                                extras={"crowd": {"piece": mesh.piece, "lod": mesh.lod, "group": mesh.group}}))
        gl.nodes.append(g.Node(name=mesh.name, mesh=len(gl.meshes) - 1, skin=0))
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
        gl.animations.append(anim)

    order = ["zombie"] + sorted(k for k in scenes if k.startswith("lod")) + ["variants", "props", "prop_lods"]
    for name in order:
        if name in scenes:
            gl.scenes.append(g.Scene(name=name, nodes=scenes[name]))
    gl.scene = 0
    gl.buffers.append(g.Buffer(byteLength=len(blob.data)))
    return gl, bytes(blob.data)


def glb_bytes(character: Character) -> bytes:
    gl, data = character_to_gltf(character)
    gl.set_binary_blob(data)
    return b"".join(gl.save_to_bytes())


def write_glb(character: Character, path: Path) -> int:
    data = glb_bytes(character)
    atomic_write_bytes(Path(path), data)
    return len(data)

