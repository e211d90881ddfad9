"""How meshes are laid out for the GPU: vertex records (packed normals, joints, weights, colours and texture
coordinates), headings, and the vertex-array formats a program reads them through.

Why so packed: on the H100 the skinned draw is bound by how many vertex attributes the shader reads, not by
the bone fetches (docs/BENCHMARKS.md, "Vertex layout"), so everything but the position goes into one uvec4.
"""

from __future__ import annotations

import moderngl
import numpy as np

from ..asset.model import PACKED_UV_SPAN, SkinnedMesh

# Per-vertex record, 28 bytes: the position and one uvec4 (see shaders/skin.vert.glsl for why two
# attributes). packed[0]: normal as three snorm10; packed[1]: joints, 4 x u8 by descending weight;
# packed[2]: weights 1-3 as unorm10 of 2w (each is at most 1/2 once sorted; weight 0 is 1 minus the rest,
# so the four sum to 1 exactly); packed[3]: colour, RGBA8.
VERTEX_DTYPE = np.dtype([("position", "<f4", 3), ("packed", "<u4", 4)])
VERTEX_FORMAT = ("3f 4u", "in_position", "in_packed")
# Pieces with a base-colour texture, 32 bytes: the position's float bits and the texture coordinate
# (unorm16 x2 across the piece's coordinate box) in one uvec4, so the shader still reads two attributes.
TEXTURED_VERTEX_DTYPE = np.dtype([("position_uv", "<u4", 4), ("packed", "<u4", 4)])
TEXTURED_VERTEX_FORMAT = ("4u 4u", "in_position", "in_packed")
# A textured piece whose coordinates span more than PACKED_UV_SPAN (unorm16 would lose texels): float
# coordinates as a third attribute, 36 bytes (and a draw about 1.4x as long on the H200).
WIDE_UV_VERTEX_DTYPE = np.dtype([("position", "<f4", 3), ("packed", "<u4", 4), ("uv", "<f4", 2)])
WIDE_UV_VERTEX_FORMAT = ("3f 4u 2f", "in_position", "in_packed", "in_uv")
LAYOUTS = {"": (VERTEX_DTYPE, VERTEX_FORMAT), "packed": (TEXTURED_VERTEX_DTYPE, TEXTURED_VERTEX_FORMAT),
            "wide": (WIDE_UV_VERTEX_DTYPE, WIDE_UV_VERTEX_FORMAT), "impostor": (None, ("2f", "in_corner"))}
WEIGHT_STEP = 1.0 / 2046.0  # a stored weight is within half of this of the float weight
UNLIT_BIT = 1 << 30  # in packed[0], above the normal's 30 bits: the vertex's piece is unlit (KHR_materials_unlit)


def rgba8(values: np.ndarray) -> np.ndarray:
    """(N, 4) integers 0-255 → (N,) uint32, R in the low byte."""
    v = np.asarray(values, np.uint32)
    return v[:, 0] | (v[:, 1] << 8) | (v[:, 2] << 16) | (v[:, 3] << 24)


def _snorm(values: np.ndarray, bits: int) -> np.ndarray:
    """Floats in [-1, 1] → two's-complement fields of `bits` bits (as uint32)."""
    scale = (1 << (bits - 1)) - 1
    q = np.rint(np.clip(values, -1.0, 1.0) * scale).astype(np.int32)
    return (q & ((1 << bits) - 1)).astype(np.uint32)


def pack_normals(normals: np.ndarray) -> np.ndarray:
    """(V, 3) unit normals → (V,) uint32 of three snorm10 fields (the skin and weapon shaders decode them)."""
    n = _snorm(np.asarray(normals, np.float64), 10)
    return n[:, 0] | (n[:, 1] << 10) | (n[:, 2] << 20)


def pack_colors(colors: np.ndarray | None, base_color, count: int) -> np.ndarray:
    """Vertex colours (white when None) times the material's base colour → (V,) RGBA8 uint32."""
    colors = colors if colors is not None else np.ones((count, 4), np.float32)
    return rgba8(np.round(np.clip(colors * np.asarray(base_color, np.float32), 0.0, 1.0) * 255.0))


def shared_buffers(ctx: moderngl.Context, meshes: list[tuple[np.ndarray, np.ndarray]]):
    """One vertex and one index buffer holding several meshes' (vertex records, indices), for one
    multi-draw-indirect over them, and each mesh's (first index, base vertex) there for its command.
    The caller owns the two buffers."""
    first_index = np.cumsum([0] + [len(i) for _, i in meshes[:-1]]).tolist()
    base_vertex = np.cumsum([0] + [len(v) for v, _ in meshes[:-1]]).tolist()
    return (ctx.buffer(np.concatenate([v for v, _ in meshes]).tobytes()), ctx.buffer(np.concatenate([i for _, i in meshes]).tobytes()),
            list(zip(first_index, base_vertex)))


def heading_snorm16(yaw: np.ndarray) -> np.ndarray:
    """(N,) headings → (N, 2) int16 snorm16 cos and sin, as instance records carry them."""
    out = np.empty((len(yaw), 2), np.int16)
    write_heading(yaw, out.view(np.uint32)[:, 0])
    return out


def write_heading(yaw: np.ndarray, out: np.ndarray) -> None:
    """(N,) headings → the records' (N,) uint32 heading field `out` (a strided column is fine): snorm16
    cos in the low half, sin in the high half. In float32 and in place, written straight into the two
    halves: |cos|, |sin| <= 1 need no clamp, and float32's error (a few 1e-8) is far below the
    snorm16 step (3.1e-5). The float64 version with its temporaries took 1.3 of the 2.3 ms that
    packing 100,000 records took on the dev container."""
    yaw = np.asarray(yaw, np.float32)
    halves = out.view(np.int16).reshape(-1, 2) if out.flags.c_contiguous else out[:, None].view(np.int16)
    scratch = np.empty(len(yaw), np.float32)
    for half, f in enumerate((np.cos, np.sin)):
        f(yaw, out=scratch)
        np.multiply(scratch, np.float32(32767.0), out=scratch)
        np.rint(scratch, out=scratch)
        halves[:, half] = scratch


def uv_layout(mesh: SkinnedMesh) -> str:
    """The vertex layout of a mesh: "" (untextured), "packed" (the coordinate beside the position,
    as unorm16 across its box) or "wide" (float coordinates, for a span packing would blur)."""
    if mesh.texture < 0:
        return ""
    corner, size = uv_box(mesh.uvs)
    return "packed" if float(np.max(size)) <= PACKED_UV_SPAN else "wide"


def pack_vertices(mesh: SkinnedMesh) -> np.ndarray:
    """Vertex records with each vertex's influences sorted by descending weight, so the shader can
    skip the third and fourth bones where their weight is zero, laid out as `uv_layout` says."""
    layout = uv_layout(mesh)
    v = np.zeros(mesh.positions.shape[0], LAYOUTS[layout][0])
    if layout == "wide":
        v["position"] = mesh.positions
        v["uv"] = mesh.uvs
    elif layout == "packed":
        v["position_uv"][:, :3] = np.ascontiguousarray(mesh.positions, np.float32).view(np.uint32)
        corner, size = uv_box(mesh.uvs)
        q = np.rint((np.asarray(mesh.uvs, np.float64) - corner) / size * 65535.0).astype(np.uint32)
        v["position_uv"][:, 3] = q[:, 0] | (q[:, 1] << 16)
    else:
        v["position"] = mesh.positions
    v["packed"][:, 0] = pack_normals(mesh.normals) | (np.uint32(UNLIT_BIT) if mesh.unlit else np.uint32(0))
    order = np.argsort(-mesh.weights, axis=1, kind="stable")
    w = np.take_along_axis(np.asarray(mesh.weights, np.float64), order, axis=1)
    w = w / w.sum(axis=1, keepdims=True)
    v["packed"][:, 1] = rgba8(np.take_along_axis(mesh.joints, order, axis=1))
    q = np.round(w[:, 1:] / WEIGHT_STEP).astype(np.uint32)  # unorm10 of 2w: w is at most 1/2 here
    v["packed"][:, 2] = q[:, 0] | (q[:, 1] << 10) | (q[:, 2] << 20)
    v["packed"][:, 3] = pack_colors(mesh.colors, mesh.base_color, len(v))
    return v


def uv_box(uvs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(corner, size) of the box around a mesh's texture coordinates that unorm16 spans (a size of 0
    becomes 1, so a constant coordinate is stored exactly). Steps are size/65535: 1/60 of a texel of a
    1024 texture for coordinates within [0, 1]."""
    uv = np.asarray(uvs, np.float64)
    corner = uv.min(axis=0)
    size = uv.max(axis=0) - corner
    return corner, np.where(size > 0.0, size, 1.0)


def unpack_uvs(packed: np.ndarray, corner, size) -> np.ndarray:
    """The texture coordinates the shader decodes from position_uv[:, 3] (the numpy twin of skin.vert.glsl)."""
    q = (packed[:, None].astype(np.uint32) >> np.array([0, 16], np.uint32)) & 0xFFFF
    return np.asarray(corner) + np.asarray(size) * (q.astype(np.float64) / 65535.0)


def unpack_weights(packed: np.ndarray) -> np.ndarray:
    """The four weights the shader decodes from packed[:, 2] (the numpy twin of skin.vert.glsl)."""
    q = (packed[:, None].astype(np.uint32) >> np.array([0, 10, 20], np.uint32)) & 0x3FF
    w123 = q.astype(np.float64) * WEIGHT_STEP
    return np.concatenate([1.0 - w123.sum(axis=1, keepdims=True), w123], axis=1)



def read_by(prog: moderngl.Program, layout: tuple) -> tuple:
    """(format, *names) of a buffer layout for one program: attributes the program does not read (the
    depth pass has no colour) become padding, so every variant shares the buffer's stride."""
    fmt, *names = layout
    per_instance = fmt.endswith("/i")
    named = iter(names)
    spec = []
    for item in fmt.removesuffix("/i").split():
        if item.endswith("x"):  # padding of the layout itself, with no attribute name
            spec.append(item)
        else:
            spec.append(item if next(named) in prog else padding(item))
    return (" ".join(spec) + ("/i" if per_instance else ""), *[n for n in names if n in prog])


def padding(fmt: str) -> str:
    """A format item's bytes as padding, for attributes a program variant does not read."""
    count = int(fmt[0]) if fmt[0].isdigit() else 1
    kind = fmt[1:] if fmt[0].isdigit() else fmt
    size = {"f": 4, "u": 4, "i": 4, "f1": 1, "u1": 1, "f2": 2, "u2": 2, "f4": 4, "u4": 4}[kind]
    return f"{count * size}x"
