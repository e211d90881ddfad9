"""The morph targets' deltas the skinned draw adds before skinning (issue 23, point 3).

Two arrays for the meshes drawn with morphs (their character's targets moved by the scene,
crowd.anim.morph), in storage buffers where the context has GL 4.3 (the draw then loads them beside the
skinning's texture fetches: docs/BENCHMARKS.md, "Morph targets", measures both), else in textures 4096
texels wide:
- ``vertices`` (R32I): one texel per vertex of those meshes, in the order their draws read them (a
  draw's ``gl_VertexID`` plus its base, ``MorphDeltas.bases``): the first texel of the vertex's block of
  deltas, or -1 where no target moves it, so an unmoved vertex costs one fetch and nothing else;
- ``deltas`` (RGB32UI): per moved vertex a block of one texel per target of its character (the agent's
  pairs name targets by the character's numbering), each texel the position delta as three snorm16 of
  ``step`` metres (the largest delta of the cast over 32767) and the normal delta as three snorm16 of
  2/32767 (a unit normal moves by at most 2), packed two to a uint.
The position step bounds the error: each delta component is within step / 2 of the float one (the largest
zombie target, 6 cm, gives 0.9 µm).
"""

from __future__ import annotations

import moderngl
import numpy as np

from ..asset.model import SkinnedMesh
from ..gl import GLStage, gpu_bytes

WIDTH = 1 << 12  # texels a row: as the palette's
SNORM = 32767.0
NORMAL_RANGE = 2.0  # a normal delta's component, at most (the difference of two unit vectors)
VERTICES_UNIT, DELTAS_UNIT = 4, 5  # texture units (0-2: the palette, 3: the shadow map, 6: the albedo array), or storage bindings


def _snorm16(values: np.ndarray) -> np.ndarray:
    """Values in units of the step → int16 fields as uint32 (rounded, clamped to ±32767)."""
    return (np.clip(np.rint(values), -SNORM, SNORM).astype(np.int32) & 0xFFFF).astype(np.uint32)


def pack_deltas(positions: np.ndarray, normals: np.ndarray, step: float) -> np.ndarray:
    """(K, 3) position and normal deltas → (K, 3) uint32 texels (skin.vert.glsl's morph_delta decodes them)."""
    p = _snorm16(np.asarray(positions, np.float64) / step)
    n = _snorm16(np.clip(np.asarray(normals, np.float64), -NORMAL_RANGE, NORMAL_RANGE) / NORMAL_RANGE * SNORM)
    return np.stack([p[:, 0] | (p[:, 1] << 16), p[:, 2] | (n[:, 0] << 16), n[:, 1] | (n[:, 2] << 16)], axis=1)


def unpack_deltas(texels: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """The numpy twin of the shader's decoding: (K, 3) uint32 → float64 position and normal deltas."""
    t = np.asarray(texels, np.uint32)
    halves = np.stack([t & 0xFFFF, t >> 16], axis=-1).reshape(len(t), 6).astype(np.uint16).view(np.int16).astype(np.float64)
    return halves[:, :3] * step, halves[:, 3:] * (NORMAL_RANGE / SNORM)


def position_step(meshes) -> float:
    """Metres a position delta's snorm16 unit stands for: the cast's largest delta component over 32767."""
    largest = max((float(np.max(np.abs(m.morph_positions))) for m in meshes if m.morph_count), default=0.0)
    return largest / SNORM if largest > 0.0 else 1.0 / SNORM


def _texture_rows(count: int) -> tuple[int, int]:
    return WIDTH, max(1, -(-count // WIDTH))


class MorphDeltas(GLStage):
    """The textures for `meshes` [(mesh, its character's target count)], each mesh's vertices at its
    place in the vertex table (in the list's order). ``bases[i]`` is the table index of mesh i's first
    vertex; ``step`` the position step; ``nbytes`` what the two textures hold."""

    def __init__(self, ctx: moderngl.Context, meshes: list[tuple[SkinnedMesh, int]], buffers: bool = False):
        self.ctx = ctx
        self.buffers = buffers
        self.step = position_step([m for m, _ in meshes])
        self.bases: list[int] = []
        table, blocks = [], []
        first_vertex, first_block = 0, 0
        for mesh, targets in meshes:
            self.bases.append(first_vertex)
            v = len(mesh.positions)
            moved = np.zeros(v, bool)
            if mesh.morph_count:
                moved = np.any(mesh.morph_positions != 0, axis=(0, 2)) | np.any(mesh.morph_normals != 0, axis=(0, 2))
            index = np.full(v, -1, np.int64)
            count = int(moved.sum())
            index[moved] = first_block + targets * np.arange(count)
            table.append(index)
            if count:
                block_p = np.zeros((count, targets, 3))
                block_n = np.zeros((count, targets, 3))
                block_p[:, mesh.morph_targets] = np.transpose(mesh.morph_positions[:, moved], (1, 0, 2))
                block_n[:, mesh.morph_targets] = np.transpose(mesh.morph_normals[:, moved], (1, 0, 2))
                blocks.append(pack_deltas(block_p.reshape(-1, 3), block_n.reshape(-1, 3), self.step))
            first_vertex += v
            first_block += count * targets
        if first_block >= 2**31:
            raise ValueError(f"{first_block:,} morph delta texels: more than a texel index holds")
        table = np.concatenate(table).astype(np.int32)
        deltas = np.concatenate(blocks) if blocks else np.zeros((1, 3), np.uint32)
        if buffers:  # std430: an int a vertex, a uvec4 a delta (its fourth word unused)
            self.vertices = ctx.buffer(table.tobytes())
            self.deltas = ctx.buffer(np.concatenate([deltas, np.zeros((len(deltas), 1), np.uint32)], axis=1).tobytes())
        else:
            self.vertices = self._texture(table, 1, "i4")
            self.deltas = self._texture(deltas, 3, "u4")

    def _texture(self, data: np.ndarray, components: int, dtype: str) -> moderngl.Texture:
        rows = data.reshape(len(data), components)
        size = _texture_rows(len(rows))
        full = np.zeros((size[0] * size[1], components), rows.dtype)
        full[:len(rows)] = rows
        tex = self.ctx.texture(size, components, full.tobytes(), dtype=dtype)
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        return tex

    @property
    def nbytes(self) -> int:
        return gpu_bytes([self.vertices, self.deltas])

    def bind(self, *programs) -> None:
        if self.buffers:
            self.vertices.bind_to_storage_buffer(VERTICES_UNIT)
            self.deltas.bind_to_storage_buffer(DELTAS_UNIT)
        else:
            self.vertices.use(VERTICES_UNIT)
            self.deltas.use(DELTAS_UNIT)
        for prog in programs:
            if self.buffers:
                prog["MorphVertices"].binding = VERTICES_UNIT
                prog["MorphDeltas"].binding = DELTAS_UNIT
            else:
                prog["u_morph_vertices"] = VERTICES_UNIT
                prog["u_morph_deltas"] = DELTAS_UNIT
            prog["u_morph_step"] = self.step

    def release(self) -> None:
        for tex in (getattr(self, "vertices", None), getattr(self, "deltas", None)):
            if tex is not None:
                tex.release()
        self.vertices = self.deltas = None
