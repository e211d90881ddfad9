"""Render stage: skinned instanced draws of the crowd, its shadow pass, and the ground.

Contract: ``CrowdRenderer.prepare(camera, instances, row_offset) -> FrameView``, then the passes, each given that view.
- ``instances`` (``Instances``): per agent a float64 world position, heading, scale, tint and, for
  each variation group ("head"), which piece it wears. Agent i's palette row is row i.
- The processor must have written this frame's palette; every pass here only reads it.
- One instanced draw per (mesh piece, LOD) with agents in it: visible agents are sorted into draws by
  the LOD their distance picks and the pieces they wear. Two cull paths behind this one interface:
  "cpu", a vectorised sphere-frustum test and a sort in numpy (any GL 3.3 context), "gpu" (GL 4.3,
  crowd/draw/gpu_cull.py), where the CPU uploads every agent's record once and a compute pass culls,
  picks LODs and fills per-draw lists that the passes draw with render_indirect, and "feedback" (GL 4.0
  to 4.2: macOS, crowd/draw/feedback_cull.py), the same decisions made by a transform-feedback pass per
  list and drawn with glDrawElementsIndirect.
- Positions are camera-relative: the CPU subtracts the camera in float64 and the GPU only sees small
  float32 numbers, so agents 1e5 m from the origin do not jitter.
- With shadows on, a depth pass draws each of the sun's cascades (crowd/draw/shadows.py) into its tile
  of one shadow map, from shadow lists of its own, culled against that cascade's box one LOD coarser,
  with the same palette rows (process once, use in every pass). With shadows off, neither the shadow
  map nor the shadow lists exist.
- With occlusion on (the gpu path), the colour cull also drops agents hidden in the previous frame's
  depth pyramid (crowd/draw/occlusion.py), which ``capture_depth`` builds after the colour passes.
- Morph targets: a piece whose character's targets the scene moves is drawn by the MORPH program. On
  the gpu path each such draw has a plain twin, and the cull (given the processor: ``prepare(...,
  processor=)``) lists there the agents whose weights move nothing, so they cost what they would
  without morphs; the cpu path draws every agent of a morph piece with the MORPH program.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import moderngl
import numpy as np
from pyglm import glm

from ..frame import Camera, Instances
from ..gl import GLStage, gpu_bytes, has_compute, load_shader
from ..settings import DEFAULTS, SETTINGS
from ..spans import over_spans
from ..lighting import FOG_COLOR, LIGHTING, SUN_DIR
from ..asset.model import PACKED_UV_SPAN, Character, SkinnedMesh
from ..asset.town import TILE
from ..anim.processor import PaletteLayout, texel_code
from ..asset.vertex_cache import best_triangle_order
from .gpu_cull import CHARACTER_SHIFT, MAX_CAST, MAX_GROUPS, RECORD_DTYPE, CullCharacter, GpuCull, GpuCullError
from .feedback_cull import FeedbackCharacter, FeedbackCull, FeedbackCullError, ListKey
from .impostors import HELD_GROUP, HELD_NONE, ImpostorTextures, held_pieces
from .materials import TEXTURE_UNIT, MaterialTextures
from .morph import MorphDeltas
from .occlusion import DepthPyramid
from .shadows import CASCADES, Cascades, cascades

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
_LAYOUTS = {"": (VERTEX_DTYPE, VERTEX_FORMAT), "packed": (TEXTURED_VERTEX_DTYPE, TEXTURED_VERTEX_FORMAT),
            "wide": (WIDE_UV_VERTEX_DTYPE, WIDE_UV_VERTEX_FORMAT), "impostor": (None, ("2f", "in_corner"))}
IMPOSTOR_PIECE = "impostor"  # the piece name of a character's impostor draw (crowd.draw.impostors)
WEIGHT_STEP = 1.0 / 2046.0  # a stored weight is within half of this of the float weight
# Per-instance record, 32 bytes: position relative to the camera and scale; palette texel of the agent's
# joint 0 (its texel code, anim.processor.texel_code), tint RGBA8, cos and sin of the heading as snorm16, and the variation choices
# (4 bits a group, which only the GPU cull reads: the record is the GPU cull's agent record too).
INSTANCE_DTYPE = RECORD_DTYPE
INSTANCE_FORMAT = ("4f 3u 4x/i", "i_position_scale", "i_packed")
CULL_PATHS = ("cpu", "gpu", "feedback")
BAKE_BOXES_UNIT = 4  # the impostor bake's per-frame boxes (the palette takes 0-2, the shadow map 3)
DEFAULT_LOD_DISTANCES = DEFAULTS["lod_distances"]  # metres: LOD0 closer than the first, LOD1 to the second, LOD2 beyond


class RenderError(ValueError):
    """Bad render input; the message is one line."""


def view_proj(camera: Camera) -> np.ndarray:
    """Camera-relative view-projection (the eye at the origin): float32 4x4, rows as in the maths
    (numpy's view of a pyglm matrix); upload it with ``gl_bytes``."""
    forward = np.asarray(camera.target, np.float64) - np.asarray(camera.eye, np.float64)
    view = glm.lookAt(glm.vec3(0.0), glm.vec3(*forward.astype(np.float32)), glm.vec3(0.0, 1.0, 0.0))
    proj = glm.perspective(math.radians(camera.fov_y), camera.aspect, camera.near, camera.far)
    return np.array(proj * view, dtype=np.float32).reshape(4, 4)


@dataclass(frozen=True)
class FrameView:
    """What ``CrowdRenderer.prepare`` decided for one frame, handed to every pass after it."""

    camera: Camera
    view_proj: np.ndarray  # float32 4x4, camera-relative
    shadow: Cascades | None  # the sun's shadow cascades (their light matrices); None without shadows
    visible: np.ndarray | None  # bool (N,): agents that survived culling (None on the GPU cull path)
    casting: np.ndarray | None = None  # bool (cascades, N): agents in each cascade's volume, whose shadows it draws (CPU path, shadows on)
    lod: np.ndarray | None = None  # int (N,): each agent's colour LOD (CPU path; its weapon's LOD follows it)
    held: np.ndarray | None = None  # bool (N,): drawn as its impostor alone, which holds its weapon (CPU path)


def frustum_planes(view_proj: np.ndarray) -> np.ndarray:
    """(6, 4) normalised planes (inside: dot(n, p) + d >= 0) of a view-projection (rows as in the maths)."""
    m = np.asarray(view_proj, np.float64)
    planes = np.stack([m[3] + m[0], m[3] - m[0], m[3] + m[1], m[3] - m[1], m[3] + m[2], m[3] - m[2]])
    return planes / np.linalg.norm(planes[:, :3], axis=1, keepdims=True)


def gl_bytes(matrix: np.ndarray) -> bytes:
    """A 4x4 matrix (rows as in the maths) in the column-major order GLSL's mat4 expects."""
    return np.ascontiguousarray(np.asarray(matrix, np.float32).T).tobytes()


def _gather(array: np.ndarray, index: np.ndarray) -> np.ndarray:
    """array[index] (rows), over spans of the index side by side (crowd.spans)."""
    out = np.empty((len(index), *array.shape[1:]), array.dtype)
    over_spans(lambda lo, hi: np.take(array, index[lo:hi], axis=0, out=out[lo:hi]), len(index))
    return out


def sphere_visible(planes: np.ndarray, centers: np.ndarray, radii: np.ndarray, reach: float | None = None, dist: np.ndarray | None = None) -> np.ndarray:
    """(N,) whether each sphere (`centers` (N, 3), `radii` (N,)) reaches inside all `planes` (and, with
    `reach`, starts within `reach` of the eye: `dist` - radius <= reach). A plane at a time over columns,
    over spans of agents side by side (crowd.spans): the (N, 3) x (3, 6) product and its (N, 6) test took
    23 ms a call at 100,000 agents in the CPU path's frame on the dev container, three calls a frame."""
    out = np.empty(len(centers), bool)

    def test(lo: int, hi: int) -> None:
        c, low = centers[lo:hi], -radii[lo:hi]
        inside = out[lo:hi]
        inside[:] = True
        d = np.empty(hi - lo)
        for a, b, z, w in planes:
            np.multiply(c[:, 0], a, out=d)
            d += c[:, 1] * b
            d += c[:, 2] * z
            d += w
            inside &= d >= low
        if reach is not None:
            inside &= dist[lo:hi] + low <= reach

    over_spans(test, len(centers))
    return out


def _rgba8(values: np.ndarray) -> np.ndarray:
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
    return _rgba8(np.round(np.clip(colors * np.asarray(base_color, np.float32), 0.0, 1.0) * 255.0))


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
    v = np.zeros(mesh.positions.shape[0], _LAYOUTS[layout][0])
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
    v["packed"][:, 0] = pack_normals(mesh.normals)
    order = np.argsort(-mesh.weights, axis=1, kind="stable")
    w = np.take_along_axis(np.asarray(mesh.weights, np.float64), order, axis=1)
    w = w / w.sum(axis=1, keepdims=True)
    v["packed"][:, 1] = _rgba8(np.take_along_axis(mesh.joints, order, axis=1))
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


@dataclass
class _Draw:
    piece: str
    lod: int
    triangles: int
    vbo: moderngl.Buffer
    ibo: moderngl.Buffer
    instances: moderngl.Buffer
    texture: int = -1  # index into Character.textures, -1: none
    layout: str = ""  # uv_layout
    uv_box: tuple = (0.0, 0.0, 1.0, 1.0)  # corner and size of the texture coordinates' unorm16 box
    vaos: dict = field(default_factory=dict)  # program key → VertexArray
    count: int = 0
    shadow_instances: list = field(default_factory=list)  # the CPU path's shadow lists, one per cascade (shadows on)
    shadow_counts: list = field(default_factory=list)  # instances in each cascade's shadow list
    first_index: int = 0  # where its indices and vertices start in the GPU path's shared buffers (vbo None)
    base_vertex: int = 0
    character: int = 0  # whose piece it is: the cast's index
    morph: bool = False  # drawn with its morph targets (crowd.draw.morph)
    morph_base: int = 0  # the morph vertex table's index of its gl_VertexID 0
    twin_of: "_Draw | None" = None  # the GPU path's plain twin of this morph draw (crowd.draw.gpu_cull)


class CrowdRenderer(GLStage):
    """Owns the meshes, instance buffers, programs, shadow map and ground of the crowd view."""

    def __init__(self, ctx: moderngl.Context, characters, pieces: tuple[str, ...] | None = None, lod_distances=DEFAULT_LOD_DISTANCES,
                 shadows: bool = True, shadow_size: int = 2048, culling: bool = True, cull_path: str = "cpu",
                 weapons_visibility: bool = False, occlusion: bool = False, town: bool = False, morphs=None, morph_buffers: bool | None = None,
                 impostors=None, impostor_distance: float = math.inf, lod_fade: float = 0.0):
        """`characters`: one Character, or the cast's, in its order (its agents come in that order,
        crowd.frame). `cull_path`: "cpu", "gpu" (a GL 4.3 context) or "feedback" (GL 4.0; see the module docstring); with
        `weapons_visibility` the GPU cull also writes each agent's visibility, for the weapons; with
        `occlusion` (the gpu path) it also drops agents hidden in the previous frame's depth. `morphs`: per
        character, whether the scene moves its morph targets (its bake has morph tracks: the processor then
        writes its agents' pairs); its pieces with targets are drawn with them, their deltas in storage
        buffers (`morph_buffers`; None: where the context has GL 4.3) or textures. `impostors`: per character,
        its ImpostorAtlas (crowd.draw.impostors) or None; an agent of a character with one is drawn as its
        impostor from `impostor_distance` metres on (its last LOD; its processor row starts with its key).
        `lod_fade`: metres past each LOD switch (the impostor's too) over which an agent is drawn at both
        LODs, cross-faded by a dither (shaders/lod_fade.glsl); 0, none."""
        self._objects: dict[str, list] = {"meshes": [], "instances": [], "programs": [], "shadow_map": [], "ground": [], "textures": [], "cull": [],
                                          "occlusion": [], "morphs": [], "impostors": []}
        self.pyramid: DepthPyramid | None = None
        self._programs: dict[tuple, moderngl.Program] = {}
        self.draws: list[_Draw] = []
        self.materials: MaterialTextures | None = None
        self.gpu: GpuCull | None = None
        self.feedback: FeedbackCull | None = None
        if cull_path not in CULL_PATHS:
            raise RenderError(f"cull path must be one of {', '.join(CULL_PATHS)}, got {cull_path!r}")
        self.cull_path = cull_path
        self.ctx = ctx
        self.town = town  # the ground shows the town's streets, sidewalks and lots (crowd.asset.town)
        self.culling = culling
        self.lod_distances = SETTINGS["lod_distances"].check(tuple(lod_distances), RenderError)
        cast = [characters] if isinstance(characters, Character) else list(characters)
        if not 1 <= len(cast) <= MAX_CAST:
            raise RenderError(f"a crowd draws 1 to {MAX_CAST} characters, got {len(cast)}")
        self.cast = cast
        self.morphs = tuple(bool(x) for x in (morphs if morphs is not None else [False] * len(cast)))
        if len(self.morphs) != len(cast):
            raise RenderError(f"morphs must say for each of the {len(cast)} characters whether its targets move, got {len(self.morphs)}")
        self.morph: MorphDeltas | None = None
        self.morph_buffers = has_compute(ctx) if morph_buffers is None else bool(morph_buffers)
        per_character = [[m for m in c.meshes if pieces is None or m.piece in pieces] for c in cast]
        for c, meshes in zip(cast, per_character):
            if not meshes:
                raise RenderError(f"character {c.name!r} has no skinned mesh to draw")
        self.lod_counts = [max(m.lod for m in meshes) + 1 for meshes in per_character]  # mesh LODs
        atlases = list(impostors) if impostors is not None else [None] * len(cast)
        if len(atlases) != len(cast):
            raise RenderError(f"impostors must give an atlas or None for each of the {len(cast)} characters, got {len(atlases)}")
        self.impostor_distance = float(impostor_distance)
        self.lod_fade = self._checked_fade(lod_fade)
        if not self.impostor_distance > 0.0:
            raise RenderError(f"the impostor distance must be a positive number of metres, got {impostor_distance}")
        # Each character with an atlas draws its agents past the impostor distance as its LOD lod_counts[k].
        self.impostor_lods = [self.lod_counts[k] if a is not None else -1 for k, a in enumerate(atlases)]
        self.lod_count = max(max(self.lod_counts), max(self.impostor_lods) + 1)
        # An armed character's impostors hold its weapons: meshes on the socket joint at the impostor's LOD,
        # chosen per agent in the group HELD_GROUP (crowd.draw.impostors.held_pieces).
        for k, c in enumerate(cast):
            if self.impostor_lods[k] >= 0:
                per_character[k] = per_character[k] + held_pieces(c, self.impostor_lods[k])
        # Variation groups, per character (group -> its pieces, in order), and every group any has, in
        # the order met: an agent's choice in group g is 4 bits at 4 g of its record.
        self.groups: list[dict[str, list[str]]] = []
        for meshes in per_character:
            groups: dict[str, list[str]] = {}
            if any(m.group == HELD_GROUP for m in meshes):
                groups[HELD_GROUP] = [HELD_NONE]  # choice 0: no weapon
            for m in meshes:
                if m.group and m.piece not in groups.setdefault(m.group, []):
                    groups[m.group].append(m.piece)
            self.groups.append(groups)
        self.group_names = list(dict.fromkeys(g for groups in self.groups for g in groups))
        if len(self.group_names) > MAX_GROUPS:
            raise RenderError(f"the cast has {len(self.group_names)} variation groups; at most {MAX_GROUPS} are drawn")
        self._piece_group = [{m.piece: m.group for m in meshes} | ({IMPOSTOR_PIECE: ""} if atlases[k] is not None else {})
                             | ({HELD_NONE: HELD_GROUP} if HELD_GROUP in self.groups[k] else {})
                             for k, meshes in enumerate(per_character)]
        # Each character's textures follow the ones before it in one list, so a draw's index is unique.
        texture_first = np.concatenate([[0], np.cumsum([len(c.textures) for c in cast])]).astype(int).tolist()
        # Untextured pieces first: on the GPU path they are one multi-draw per pass (below), or two: those
        # drawn without morph targets, then those drawn with them (another program).
        shared = []  # (vertices, indices) of the GPU path's untextured pieces, drawn from shared buffers
        morphing = lambda k, m: self.morphs[k] and m.morph_count > 0  # noqa: E731
        ordered = sorted(((k, m) for k, meshes in enumerate(per_character) for m in meshes),
                         key=lambda km: (km[1].texture >= 0, morphing(*km), km[0], km[1].lod, km[1].piece))
        morph_meshes = []  # the meshes drawn with their targets, in the morph vertex table's order
        for k, m in ordered:
            vertices, indices = pack_vertices(m), best_triangle_order(m.indices, len(m.positions))
            box = tuple(float(x) for x in np.concatenate(uv_box(m.uvs))) if m.texture >= 0 else (0.0, 0.0, 1.0, 1.0)
            texture = texture_first[k] + m.texture if m.texture >= 0 else -1
            if morphing(k, m):
                morph_meshes.append((m, len(cast[k].morphs)))
            if cull_path == "gpu" and m.texture < 0:
                shared.append((vertices, indices))
                self.draws.append(_Draw(m.piece, m.lod, m.triangle_count, None, None, None, texture, "", box, character=k, morph=morphing(k, m)))
                continue
            vbo = self._own("meshes", ctx.buffer(vertices.tobytes()))
            ibo = self._own("meshes", ctx.buffer(indices.tobytes()))
            # The CPU path's instance records, per draw; the GPU path draws from the cull's lists.
            inst = self._own("instances", ctx.buffer(reserve=INSTANCE_DTYPE.itemsize)) if cull_path == "cpu" else None
            self.draws.append(_Draw(m.piece, m.lod, m.triangle_count, vbo, ibo, inst, texture, uv_layout(m), box, character=k, morph=morphing(k, m)))
        # The GPU path's untextured draws (draws 0 .. merged - 1): one vertex and one index buffer, so a pass
        # draws them all with one glMultiDrawElementsIndirect instead of a call each (69 calls a frame for
        # the built-in zombie with shadows; each costs the CPU a call through moderngl and the driver).
        self.merged = len(shared)
        self._merged_buffers = None
        if self.merged:
            vbo, ibo, starts = shared_buffers(ctx, shared)
            self._merged_buffers = (self._own("meshes", vbo), self._own("meshes", ibo))
            for draw, (first, base) in zip(self.draws, starts):  # the shared pieces are draws 0 .. merged - 1
                draw.first_index, draw.base_vertex = first, base
        self.merged_plain = sum(1 for d in self.draws[:self.merged] if not d.morph)  # then the shared morphing ones
        if morph_meshes:
            self.morph = self._own("morphs", MorphDeltas(ctx, morph_meshes, self.morph_buffers))
            for draw, base in zip([d for d in self.draws if d.morph], self.morph.bases):  # the table's order is the draws'
                draw.morph_base = base - draw.base_vertex  # shared: gl_VertexID counts from the buffer's start
        if cull_path == "gpu" and morph_meshes:
            # Each morph draw's plain twin: the same geometry drawn by the program without morph code, for
            # the agents whose weights move nothing (the GPU cull routes them), so that they cost what
            # they would without morphs. The merged twins join the plain multi-draw.
            twin = lambda d: replace(d, morph=False, twin_of=d, vaos={})  # noqa: E731
            merged_twins = [twin(d) for d in self.draws[:self.merged] if d.morph]
            self.draws[self.merged_plain:self.merged_plain] = merged_twins
            self.draws += [twin(d) for d in self.draws[self.merged + len(merged_twins):] if d.morph]
            self.merged += len(merged_twins)
            self.merged_plain += len(merged_twins)
        # One quad draw per character with an atlas, after every mesh draw (so the cull's first common
        # piece stays a mesh); its textures and the quad are the "impostors" group's.
        self.impostors: list = [None] * len(cast)
        if any(a is not None for a in atlases):
            quad = self._own("impostors", ctx.buffer(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32).tobytes()))
            quad_indices = self._own("impostors", ctx.buffer(np.array([0, 1, 2, 0, 2, 3], np.uint32).tobytes()))
            for k, atlas in enumerate(atlases):
                if atlas is None:
                    continue
                self.impostors[k] = self._own("impostors", ImpostorTextures(ctx, atlas))
                inst = self._own("instances", ctx.buffer(reserve=INSTANCE_DTYPE.itemsize)) if cull_path == "cpu" else None
                self.draws.append(_Draw(IMPOSTOR_PIECE, self.impostor_lods[k], 2, quad, quad_indices, inst, -1, "impostor", character=k))
        self._merged_vaos: dict = {}
        for draw in self.draws if shadows else ():
            draw.shadow_counts = [0] * CASCADES
            if cull_path == "cpu":
                draw.shadow_instances = [self._own("instances", ctx.buffer(reserve=INSTANCE_DTYPE.itemsize)) for _ in range(CASCADES)]
        # Only the textures a drawn piece uses reach the GPU, and none when no piece has one.
        used = {d.texture for d in self.draws if d.texture >= 0}
        self.materials = self._own("textures", MaterialTextures(ctx, [t for c in cast for t in c.textures], used)) if used else None
        # A sphere around each character's bind pose, widened for poses that reach out or lie down (death).
        self.bounds = np.zeros((len(cast), 4))
        for k, meshes in enumerate(per_character):
            allpos = np.concatenate([m.positions for m in meshes]).astype(np.float64)
            lo, hi = allpos.min(axis=0), allpos.max(axis=0)
            self.bounds[k, :3] = (lo + hi) / 2.0
            self.bounds[k, 3] = float(np.linalg.norm(hi - lo) * 0.5 * 1.3)
        if cull_path == "gpu":
            slot, characters = {}, []
            for k, groups in enumerate(self.groups):
                common = [p for p in dict.fromkeys(d.piece for d in self.draws if d.character == k) if not self._piece_group[k][p]]
                first = len(slot)
                for p in common:
                    slot[k, p] = len(slot)
                group_slots = []
                for group in self.group_names:
                    group_slots.append(len(slot) if group in groups else -1)
                    for piece in groups.get(group, ()):
                        slot[k, piece] = len(slot)
                characters.append(CullCharacter(first, len(common), tuple(group_slots), self.lod_counts[k], tuple(float(x) for x in self.bounds[k]),
                                                self.impostor_distance if self.impostor_lods[k] >= 0 else math.inf))
            choices = [max(len(g.get(name, ())) for g in self.groups) for name in self.group_names]
            try:
                index = {id(d): i for i, d in enumerate(self.draws)}
                self.gpu = self._own("cull", GpuCull(ctx, [(d.lod, slot[d.character, d.piece], d.triangles * 3, d.first_index, d.base_vertex, d.character,
                                                            -1 if d.twin_of is None else index[id(d.twin_of)])
                                                           for d in self.draws], characters, choices, weapons_visibility, CASCADES if shadows else 0))
            except GpuCullError as exc:
                raise RenderError(f"{exc} (the cpu cull path has no such limit)") from None
            self.gpu.lod_fade = self.lod_fade
            for draw in self.draws:  # every draw reads its list out of the one list buffer (baseInstance)
                draw.instances = self.gpu.lists
        if cull_path == "feedback":
            keys = []
            for d in self.draws:
                group = self._piece_group[d.character][d.piece]
                g = self.group_names.index(group) if group else -1
                keys.append((ListKey(d.character, d.lod, g, self.groups[d.character][group].index(d.piece) if group else 0), d.triangles * 3))
            characters = [FeedbackCharacter(self.lod_counts[k], tuple(float(x) for x in self.bounds[k]),
                                            self.impostor_distance if self.impostor_lods[k] >= 0 else math.inf) for k in range(len(cast))]
            try:
                self.feedback = self._own("cull", FeedbackCull(ctx, keys, characters, CASCADES if shadows else 0, weapons_visibility))
            except FeedbackCullError as exc:
                raise RenderError(f"{exc} (the cpu cull path has no such limit)") from None
            self.feedback.lod_fade = self.lod_fade
            for d, draw in enumerate(self.draws):  # each draw reads its list's buffer
                draw.instances = self.feedback.list_buffer(d)
        self.shadows = shadows
        self.shadow_size = int(shadow_size)
        self.shadow_map = None
        self._shadow_fbo = None
        if shadows:  # one tile per cascade, side by side (crowd.draw.shadows)
            self.shadow_map = self._own("shadow_map", ctx.depth_texture((CASCADES * self.shadow_size, self.shadow_size)))
            self.shadow_map.compare_func = "<="
            self.shadow_map.filter = (moderngl.LINEAR, moderngl.LINEAR)
            self.shadow_map.repeat_x = self.shadow_map.repeat_y = False
            self._shadow_fbo = self._own("shadow_map", ctx.framebuffer(depth_attachment=self.shadow_map))
        ground_prog = self._program("ground", False)
        extent = 1000.0
        quad = np.array([[-extent, -extent], [extent, -extent], [extent, extent], [-extent, -extent], [extent, extent], [-extent, extent]], np.float32)
        self._ground_vbo = self._own("ground", ctx.buffer(quad.tobytes()))
        self._ground_vao = self._own("ground", ctx.vertex_array(ground_prog, [(self._ground_vbo, "2f", "in_position")]))
        self.sun_dir = np.array(SUN_DIR)
        self.crowd_box: tuple[np.ndarray, np.ndarray] | None = None  # world (lo, hi) the agents stand in; None: measured each frame
        self.set_occlusion(occlusion)
        self.last = {"triangles": 0, "instances": 0, "visible": 0, "draws": 0, "lod_counts": [0] * self.lod_count, "shadow_instances": 0,
                     "cast_visible": [0] * len(self.cast)}

    # -- resources

    def _own(self, group, obj):
        self._objects[group].append(obj)
        return obj

    def _program(self, kind: str, skinned: bool | str, layout: str = "", morph: bool = False) -> moderngl.Program:
        """kind: color, depth or ground; skinned: True, or False for the benchmark's unskinned ceiling;
        layout: a textured piece's vertex layout ("packed" or "wide", see uv_layout), "" for none; morph:
        pieces drawn with their morph targets."""
        key = (kind, skinned, layout, morph)
        if key in self._programs:
            return self._programs[key]
        defines = {}
        if self.shadows:
            defines.update(SHADOWS=1, CASCADES=CASCADES)
        if self.lod_fade > 0.0 and kind == "color":
            defines["LOD_FADE"] = 1
        if kind == "ground":
            if self.town:
                defines["TOWN"] = 1
            prog = self.ctx.program(vertex_shader=load_shader("ground.vert.glsl"), fragment_shader=load_shader("ground.frag.glsl", defines))
            if self.town:
                from ..asset.town import SIDEWALK, STREET

                prog["u_tile"], prog["u_street"], prog["u_sidewalk"] = TILE, STREET, SIDEWALK
        elif layout == "impostor":
            vdefs = {"DEPTH_ONLY": 1} if kind == "depth" else {}
            prog = self.ctx.program(vertex_shader=load_shader("impostor.vert.glsl", vdefs),
                                    fragment_shader=load_shader("impostor.frag.glsl", {**defines, **vdefs}))
        else:
            vdefs = {} if skinned else {"UNSKINNED": 1}
            if "LOD_FADE" in defines:
                vdefs["LOD_FADE"] = 1
            if kind == "depth":
                vdefs["DEPTH_ONLY"] = 1
                frag = load_shader("depth.frag.glsl")
            else:
                if layout:
                    defines["TEXTURED"] = 1
                if kind == "bake":  # an impostor atlas's cells (crowd.draw.impostors): unlit, no shadows
                    defines = {k: v for k, v in defines.items() if k not in ("SHADOWS", "CASCADES")}
                    defines["IMPOSTOR_BAKE"] = vdefs["IMPOSTOR_BAKE"] = 1
                frag = load_shader("skin.frag.glsl", defines)
            if layout:
                vdefs["TEXTURED"] = 1
            if layout == "wide":
                vdefs["WIDE_UV"] = 1
            if morph:
                vdefs["MORPH"] = 1
                if self.morph_buffers:
                    vdefs["MORPH_BUFFERS"] = 1
            prog = self.ctx.program(vertex_shader=load_shader("skin.vert.glsl", vdefs), fragment_shader=frag)
        for name, unit in (("u_palette0", 0), ("u_palette1", 1), ("u_palette2", 2)):
            if name in prog:
                prog[name] = unit
        if "u_shadow_map" in prog:
            prog["u_shadow_map"] = 3
        if "u_albedo" in prog:
            prog["u_albedo"] = TEXTURE_UNIT
        self._programs[key] = self._own("programs", prog)
        return prog

    def _merged_vao(self, kind: str, skinned: bool, morph: bool = False) -> moderngl.VertexArray:
        """The GPU path's vertex array over the untextured pieces' shared buffers and a pass's lists (for
        the program of the pieces drawn without, or with, morph targets)."""
        key = (kind, skinned, morph)
        if key not in self._merged_vaos:
            prog = self._program(kind, skinned, "", morph)
            instances = self.gpu.shadow_lists if kind == "depth" else self.gpu.lists
            vbo, ibo = self._merged_buffers
            content = [(vbo, *_read_by(prog, _LAYOUTS[""][1])), (instances, *_read_by(prog, INSTANCE_FORMAT))]
            self._merged_vaos[key] = self._own("programs", self.ctx.vertex_array(prog, content, index_buffer=ibo, index_element_size=4))
        return self._merged_vaos[key]

    def _render_merged(self, kind: str, skinned: bool, cascade: int = 0, morph: bool = False) -> None:
        """The untextured draws of a pass drawn without (or with) morph targets in one multi-draw: their
        commands are 0 .. merged_plain - 1 (merged_plain .. merged - 1), a cascade's after the cascades
        before it. Unskinned (the benchmark's ceiling, which reads no palette) they are all one multi-draw."""
        first, count = (self.merged_plain, self.merged - self.merged_plain) if morph else (0, self.merged_plain if skinned else self.merged)
        if not count:
            return
        commands = self.gpu.shadow_commands if kind == "depth" else self.gpu.commands
        vao = self._merged_vao(kind, skinned, morph)
        if morph:
            vao.program["u_morph_vertex_base"] = self.draws[first].morph_base
        vao.render_indirect(commands, moderngl.TRIANGLES, count=count, first=first + (cascade * len(self.draws) if kind == "depth" else 0))

    def _vao(self, draw: _Draw, kind: str, skinned: bool, cascade: int = 0, index: int = 0) -> moderngl.VertexArray:
        key = (kind, skinned, cascade)
        if key not in draw.vaos:
            prog = self._draw_program(draw, kind, skinned)
            if kind == "depth":  # the shadow pass reads the shadow lists (the GPU path's: one buffer, by baseInstance)
                if self.gpu is not None:
                    instances = self.gpu.shadow_lists
                elif self.feedback is not None:
                    instances = self.feedback.list_buffer(index, cascade)
                else:
                    instances = draw.shadow_instances[cascade]
            else:
                instances = draw.instances
            content = [(draw.vbo, *_read_by(prog, _LAYOUTS[draw.layout][1])), (instances, *_read_by(prog, INSTANCE_FORMAT))]
            draw.vaos[key] = self._own("programs", self.ctx.vertex_array(prog, content, index_buffer=draw.ibo, index_element_size=4))
        return draw.vaos[key]

    def _variants(self) -> list[tuple[str, bool]]:
        """The program variants a pass runs: one per (vertex layout, drawn with morph targets) among the pieces."""
        return sorted({(d.layout, d.morph) for d in self.draws})

    def _draw_program(self, draw: _Draw, kind: str, skinned: bool) -> moderngl.Program:
        return self._program(kind, skinned, draw.layout, draw.morph and skinned is True)

    @staticmethod
    def _checked_fade(metres) -> float:
        try:
            value = float(metres)
        except (TypeError, ValueError):
            raise RenderError(f"the LOD fade must be a number of metres, got {metres!r}") from None
        if not 0.0 <= value < 1e6:
            raise RenderError(f"the LOD fade must be 0 to 1e6 metres, got {metres}")
        return value

    def set_lod_fade(self, metres: float) -> None:
        """Cross-fade each LOD switch over `metres` (0: switch at once). The colour programs compile the
        fade's dither only while there is one (a discard costs the depth test its early pass), so
        switching it on or off builds them again."""
        metres = self._checked_fade(metres)
        if (metres > 0.0) != (self.lod_fade > 0.0):  # the colour programs and their vertex arrays go
            stale = [self._programs.pop(key) for key in [k for k in self._programs if k[0] == "color"]]
            stale += [self._merged_vaos.pop(key) for key in [k for k in self._merged_vaos if k[0] == "color"]]
            for draw in self.draws:
                stale += [draw.vaos.pop(key) for key in [k for k in draw.vaos if k[0] == "color"]]
            self._objects["programs"] = [o for o in self._objects["programs"] if all(o is not s for s in stale)]
            for obj in reversed(stale):
                obj.release()
        self.lod_fade = metres
        for cull in (self.gpu, self.feedback):
            if cull is not None:
                cull.lod_fade = metres

    def set_impostor_distance(self, metres: float) -> None:
        """Draw impostors from `metres` on (both cull paths read it each frame)."""
        if not float(metres) > 0.0:
            raise RenderError(f"the impostor distance must be a positive number of metres, got {metres}")
        self.impostor_distance = float(metres)
        for cull in (self.gpu, self.feedback):
            if cull is not None:
                cull.characters = [c._replace(impostor_start=self.impostor_distance if self.impostor_lods[k] >= 0 else math.inf)
                                   for k, c in enumerate(cull.characters)]

    def set_occlusion(self, on: bool) -> None:
        """Keep (or drop) the depth pyramid occlusion culling tests against; the cpu path has none."""
        if on and self.gpu is not None and self.pyramid is None:
            self.pyramid = DepthPyramid(self.ctx)
            self._own("occlusion", self.pyramid)
        elif not on and self.pyramid is not None:
            self._objects["occlusion"].remove(self.pyramid)
            self.pyramid.release()
            self.pyramid = None

    def capture_depth(self, framebuffer, view: "FrameView") -> None:
        """After the frame's colour passes: its depth into the pyramid the next frame's cull tests against."""
        if self.pyramid is not None:
            self.pyramid.capture(framebuffer, view.view_proj, view.camera.eye)

    def gpu_bytes(self) -> dict[str, int]:
        out = {group: gpu_bytes(objs) for group, objs in self._objects.items() if group not in ("programs", "textures", "cull", "occlusion")}
        if self.materials is not None:
            out["textures"] = self.materials.gpu_bytes()
        if self.gpu is not None or self.feedback is not None:
            out["cull"] = (self.gpu or self.feedback).gpu_bytes()
        if self.pyramid is not None:
            out["occlusion"] = self.pyramid.gpu_bytes()
        out["morphs"] = 0 if self.morph is None else self.morph.nbytes
        out["impostors"] = gpu_bytes(self._objects["impostors"]) + sum(t.gpu_bytes() for t in self.impostors if t is not None)
        return out

    def release(self) -> None:
        for objs in self._objects.values():
            for obj in reversed(objs):
                obj.release()
        self._objects = {k: [] for k in self._objects}
        self._programs.clear()
        self.draws = []
        self.materials = None
        self.gpu = None
        self.feedback = None
        self.pyramid = None
        self.morph = None

    # -- per frame

    @staticmethod
    def clear_color() -> tuple[float, float, float]:
        return tuple(c ** (1 / 2.2) for c in FOG_COLOR)

    def prepare(self, camera: Camera, instances: Instances, row_offset=0, cull_now: bool = True, palette: PaletteLayout | None = None,
                processor=None) -> "FrameView":
        """Cull, pick LODs, sort agents into draws and upload their records (the CPU path), or upload
        every agent's record and dispatch the GPU cull that does the rest (the GPU path). Returns what
        every later pass of this frame receives (the view and light matrices, and the visible set where
        the CPU knows it: None on the GPU path).
        `row_offset` (an int, or one per agent) is the first palette row of the ring slot each agent's
        palette is read from (see AnimationProcessor.row_offset); `palette` the processor's layout (None:
        the one the processor makes for these characters and counts). With `cull_now` False the GPU path
        uploads the records and leaves the dispatch to ``cull()``, so a caller can time the GPU's part alone.
        `processor`: the one whose palette the passes read, run for this frame already; on the GPU path
        its morph pairs send agents moving no target to the plain twins (None: to the morph draws)."""
        camera.validate()
        instances.validate(self.groups)
        counts = instances.counts()
        if len(counts) != len(self.cast):
            raise RenderError(f"instances of {len(counts)} characters, the renderer draws {len(self.cast)}")
        matrix = view_proj(camera)
        shadow = self.light_cascades(camera, instances) if self.shadows else None
        eye = np.asarray(camera.eye, np.float64)
        palette = palette or PaletteLayout.make([c.skeleton.joint_count for c in self.cast], counts)
        self.palette = palette  # the layout this frame's records address (tests and benchmarks read lists back by it)
        if tuple(p.morph for p in palette.parts) != self.morphs:
            raise RenderError(f"the palette holds morph pairs for characters {[p.morph for p in palette.parts]}, the draw reads them for "
                              f"{list(self.morphs)}: build both from the same bakes")
        # Shadows come from lists of their own, culled against the sun's volume (an agent outside the
        # view still shadows into it) one LOD coarser: the colour lists need no margin.
        if self.culls_on_gpu:  # the compute or the feedback cull: the same upload, the dispatch in cull()
            try:
                (self.gpu or self.feedback).upload(self._all_records(instances, eye, row_offset, palette), counts)
            except (GpuCullError, FeedbackCullError) as exc:
                raise RenderError(f"{exc} (the cpu cull path needs no lists: --cull cpu)") from None
            self.refresh_counts()  # the newest frame the GPU has finished (none queued for 0 agents: 0)
            self._pending = (frustum_planes(matrix), None if shadow is None else (np.stack([frustum_planes(m) for m in shadow.view_proj]), shadow.reach_m), eye)
            if cull_now:
                self.cull(processor)
            return FrameView(camera, matrix, shadow, None)
        n = len(instances)
        kind = self._kinds(counts)
        # Each agent's bounding sphere (camera-relative, float64), its distance, the LOD starts it has passed
        # and its LOD: over spans of agents side by side (crowd.spans).
        centers, radii, dist = np.empty((n, 3)), np.empty(n), np.empty(n)
        passed, lod, as_impostor = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, bool)
        starts = np.asarray(self.lod_distances, np.float64)
        tops, impostor_lods = np.asarray(self.lod_counts, np.int64) - 1, np.asarray(self.impostor_lods, np.int64)

        def place(lo: int, hi: int) -> None:
            scale = instances.scale[lo:hi].astype(np.float64)
            k = 0 if kind is None else kind[lo:hi]
            bound = self.bounds[k]  # (4,), or (span, 4) for a cast
            c = centers[lo:hi]
            for axis in range(3):
                np.subtract(instances.position[lo:hi, axis], eye[axis], out=c[:, axis])
                c[:, axis] += bound[..., axis] * scale
            np.multiply(bound[..., 3], scale, out=radii[lo:hi])
            np.sqrt(c[:, 0] * c[:, 0] + c[:, 1] * c[:, 1] + c[:, 2] * c[:, 2], out=dist[lo:hi])
            passed[lo:hi] = np.searchsorted(starts, dist[lo:hi], side="right")
            impostor_lod = impostor_lods[k]
            np.logical_and(dist[lo:hi] >= self.impostor_distance, impostor_lod >= 0, out=as_impostor[lo:hi])
            lod[lo:hi] = np.where(as_impostor[lo:hi], impostor_lod, np.minimum(passed[lo:hi], tops[k]))

        over_spans(place, n)
        visible = sphere_visible(frustum_planes(matrix), centers, radii) if self.culling and n else np.ones(n, bool)
        top = tops[0] if kind is None else tops[kind]
        impostor_lod = impostor_lods[0 if kind is None else kind]
        shown = np.flatnonzero(visible).astype(np.uint32)
        records = self._all_records(instances, eye, row_offset, palette)  # once, for the colour and the shadow lists
        listed, listed_lod, listed_records = self._fade_entries(shown, lod, passed, dist, as_impostor, top, records)
        drawn = self._upload_lists(instances, records, listed, listed_lod, kind, "instances", records=listed_records)
        self.last = {"triangles": int(sum(c * d.triangles for c, d in zip(drawn, self.draws))), "instances": int(sum(drawn)),
                     "visible": len(shown), "draws": sum(1 for c in drawn if c),
                     "lod_counts": np.bincount(lod[shown], minlength=self.lod_count).tolist(), "shadow_instances": 0,
                     "cast_visible": [len(shown)] if kind is None else np.bincount(kind[shown], minlength=len(self.cast)).tolist()}
        for draw, c in zip(self.draws, drawn):
            draw.count = c
        lit = None
        if self.shadows:
            lit = np.stack([sphere_visible(frustum_planes(m), centers, radii, reach, dist) if self.culling and n else np.ones(n, bool)
                            for m, reach in zip(shadow.view_proj, shadow.reach_m)])
            shadow_lod = np.where(as_impostor, impostor_lod, np.minimum(lod + 1, top))
            for k, in_cascade in enumerate(lit):
                casting = np.flatnonzero(in_cascade).astype(np.uint32)
                drawn = self._upload_lists(instances, records, casting, shadow_lod[casting], kind, "shadow_instances", k)
                for draw, c in zip(self.draws, drawn):
                    draw.shadow_counts[k] = c
                self.last["shadow_instances"] += int(sum(drawn))
        # Held: an impostor past its fade band (its impostor alone is drawn, holding the weapon).
        return FrameView(camera, matrix, shadow, visible, lit, lod, as_impostor & (dist >= self.impostor_distance + self.lod_fade))

    def _fade_entries(self, shown, lod, passed, dist, as_impostor, top, records):
        """The CPU path's colour list entries: each shown agent at its LOD, and those within lod_fade of
        the switch behind them again at the finer LOD, each record's tint alpha carrying its fade code
        (shaders/lod_fade.glsl; 255 for none), as the GPU cull lists them."""
        entries = _gather(records, shown)
        tint = entries["packed"][:, 1]
        tint |= np.uint32(0xFF000000)
        if not self.lod_fade or not len(shown):
            return shown, lod[shown], entries
        d = dist[shown]
        raw = passed[shown]
        impostor = as_impostor[shown]
        starts = np.asarray(self.lod_distances, np.float64)
        boundary = np.where(impostor, self.impostor_distance, np.where(raw > 0, starts[np.maximum(raw - 1, 0)], -1.0))
        top_shown = np.broadcast_to(top, dist.shape)[shown]
        finer = np.where(impostor, np.minimum(raw, top_shown), np.minimum(raw - 1, top_shown))
        fading = (boundary >= 0.0) & (d < boundary + self.lod_fade) & (finer != lod[shown])
        # float32, as the GPU cull works it out
        through = np.clip((d.astype(np.float32) - boundary.astype(np.float32)) / np.float32(self.lod_fade), 0.0, 1.0)
        code = (through * 127.0 + 0.5).astype(np.uint32)
        tint[fading] = (tint[fading] & np.uint32(0x00FFFFFF)) | ((np.uint32(128) | code[fading]) << np.uint32(24))
        near = entries[fading].copy()
        near["packed"][:, 1] = (near["packed"][:, 1] & np.uint32(0x00FFFFFF)) | (code[fading] << np.uint32(24))
        return (np.concatenate([shown, shown[fading]]), np.concatenate([lod[shown], finer[fading]]),
                np.concatenate([entries, near]))

    def _kinds(self, counts: tuple[int, ...]) -> np.ndarray | None:
        """Each agent's character (uint8 (N,)) for a cast of these counts, kept while they stay; None for one character."""
        if len(self.cast) == 1:
            return None
        if getattr(self, "_kind_counts", None) != counts:
            self._kind_counts = counts
            self._kind = np.repeat(np.arange(len(counts), dtype=np.uint8), counts)
        return self._kind

    def _upload_lists(self, instances: Instances, all_records: np.ndarray, shown: np.ndarray, lod: np.ndarray, kind: np.ndarray | None,
                      buffer: str, cascade: int = 0, records: np.ndarray | None = None) -> list[int]:
        """The CPU path's lists: the records of agents `shown` at LODs `lod` (of characters `kind`, None:
        the one), sorted once per variation group so that each draw's instances are one contiguous slice
        (a boolean mask per draw cost 12 passes over the crowd), written into each draw's `buffer`
        ("instances", or "shadow_instances" of that `cascade`). `all_records`: every agent's record
        (``_all_records``), or `records`: one per entry of `shown` (an agent may be listed twice, across a
        LOD fade). Returns each draw's count."""
        records = _gather(all_records, shown) if records is None else records
        lods = self.lod_count
        slices = {}  # group ("" for pieces every agent wears) → (records sorted by draw key, start offsets per key)
        for group in ["", *self.group_names]:
            choices = max(len(g.get(group, ())) for g in self.groups) if group else 1
            variant = instances.variant.get(group) if group else None
            key = np.empty(len(shown), np.uint16)

            def draw_key(lo: int, hi: int) -> None:  # (character, LOD, choice), over spans of the list (crowd.spans)
                k = lod[lo:hi] if kind is None else kind[shown[lo:hi]].astype(np.int64) * lods + lod[lo:hi]
                key[lo:hi] = k * choices + (variant[shown[lo:hi]] if variant is not None else 0)

            over_spans(draw_key, len(shown))
            order = np.argsort(key, kind="stable")  # a radix sort for 16-bit keys
            starts = np.concatenate([[0], np.cumsum(np.bincount(key, minlength=len(self.cast) * lods * choices))])
            slices[group] = (_gather(records, order), starts, choices)
        counts = []
        for draw in self.draws:
            groups = self.groups[draw.character]
            group = self._piece_group[draw.character][draw.piece]
            sorted_records, starts, choices = slices[group]
            k = (draw.character * lods + draw.lod) * choices + (groups[group].index(draw.piece) if group else 0)
            chosen = sorted_records[starts[k]:starts[k + 1]]
            target = draw.instances if buffer == "instances" else draw.shadow_instances[cascade]
            size = max(chosen.nbytes, INSTANCE_DTYPE.itemsize)  # exact: a smaller crowd frees what it no longer needs
            if target.size != size:
                target.orphan(size)
            if len(chosen):
                target.write(chosen)  # (a contiguous slice: no copy)
            counts.append(len(chosen))
        return counts

    def _all_records(self, instances: Instances, eye: np.ndarray, row_offset, palette: PaletteLayout) -> np.ndarray:
        """Every agent's instance record, as the shaders (and the GPU cull) read them, written into
        arrays kept from frame to frame: the palette texel code of agent i is a fixed base plus its ring
        slot's first row, so only that addition runs per frame (the processor keeps x under 4096 and
        its rows under 2^20: texel_code); the character bits are fixed while the cast's counts are."""
        n = len(instances)
        if getattr(self, "_scratch_layout", None) != palette:
            self._scratch_layout = palette
            self._scratch = np.empty(n, INSTANCE_DTYPE)
            x, y = palette.texel(np.arange(n), 0, 0)
            self._texel_base = texel_code(x, y)
            kind = self._kinds(palette.counts)
            self._character_bits = None if kind is None else kind.astype(np.uint32) << np.uint32(CHARACTER_SHIFT)
        if len(self._scratch) != n:
            raise RenderError(f"{n} instances, but the palette holds {palette.agents} agents")
        records, fields = self._scratch, self._scratch["packed"]
        position = records["position_scale"]
        tint = instances.tint
        packed_tint = tint.dtype == np.uint8 and tint.flags.c_contiguous
        variants = [(g, instances.variant.get(group)) for g, group in enumerate(self.group_names)]
        row_code = texel_code(0, row_offset)

        def pack(lo: int, hi: int) -> None:  # agents lo..hi, beside the other spans (crowd.spans)
            # The subtraction in float64 (agents far from the origin), rounded once into the record; a column
            # at a time, which is 3 times as fast as numpy's (N, 3) into strided (N, 3) broadcast.
            for c in range(3):
                np.subtract(instances.position[lo:hi, c], eye[c], out=position[lo:hi, c], casting="unsafe")
            position[lo:hi, 3] = instances.scale[lo:hi]
            np.add(self._texel_base[lo:hi], row_code if row_code.ndim == 0 else row_code[lo:hi], out=fields[lo:hi, 0], casting="unsafe")
            fields[lo:hi, 1] = tint[lo:hi].view("<u4")[:, 0] if packed_tint else _rgba8(tint[lo:hi])
            write_heading(instances.yaw[lo:hi], fields[lo:hi, 2])
            bits = fields[lo:hi, 3]
            if self._character_bits is None:
                bits[:] = 0
            else:
                bits[:] = self._character_bits[lo:hi]
            for g, v in variants:
                if v is not None:
                    bits |= v[lo:hi].astype(np.uint32) << np.uint32(4 * g)

        over_spans(pack, n)
        return records

    def cull(self, processor=None) -> bool:
        """The GPU path's cull dispatch for what `prepare(cull_now=False)` uploaded; False when there
        is nothing to do (the CPU path, or already done). `processor`: as for ``prepare``."""
        pending, self._pending = getattr(self, "_pending", None), None
        if not self.culls_on_gpu or pending is None:
            return False
        planes, light_planes, eye = pending  # the view's planes, (each cascade's planes, reach), the eye
        if self.feedback is not None:
            self.feedback.run(planes, self.lod_distances, self.culling, *(light_planes if light_planes is not None else (None, None)))
            return True
        self.gpu.run(planes, 0.0, self.lod_distances, self.culling, occlusion=None if self.pyramid is None else (self.pyramid, eye), palette=processor)
        if light_planes is not None:
            self.gpu.run_shadow(light_planes[0], self.lod_distances, self.culling, light_planes[1], palette=processor)
        return True

    def refresh_counts(self, wait: bool = False) -> None:
        """``last`` on the GPU path: the newest counts the GPU has handed back (a frame or two old;
        `wait` finishes the frames queued: stats at the end of a run, tests). A no-op on the CPU path."""
        cull = self.gpu or self.feedback
        if cull is None:
            return
        counts = cull.counts(wait).astype(np.int64)
        agents = cull.agent_counts().astype(np.int64)  # (characters, LOD slots): each kept agent once
        lod_counts = [int(x) for x in agents.sum(axis=0)[: self.lod_count]]
        cast_visible = [int(x) for x in agents.sum(axis=1)]
        for draw, c in zip(self.draws, counts):
            draw.count = int(c)
        shadow = cull.shadow_counts(wait).astype(np.int64)  # (cascades, draws)
        for d, draw in enumerate(self.draws):
            draw.shadow_counts = [int(c) for c in shadow[:, d]]
        self.last = {"triangles": int(sum(c * d.triangles for c, d in zip(counts, self.draws))), "instances": int(counts.sum()),
                     "visible": int(sum(lod_counts)), "draws": int(np.count_nonzero(counts)), "lod_counts": lod_counts,
                     "shadow_instances": int(shadow.sum()), "cast_visible": cast_visible}

    @property
    def culls_on_gpu(self) -> bool:
        """Whether the lists are made on the GPU (the gpu and feedback paths), by ``cull()``."""
        return self.gpu is not None or self.feedback is not None

    def draws_anything(self, agents: int) -> bool:
        """Whether this frame's passes have instances to draw (the GPU paths cannot know: any agent may be)."""
        return agents > 0 if self.culls_on_gpu else bool(self.last["instances"])

    def _render(self, index: int, draw: _Draw, kind: str, skinned: bool, cascade: int = 0) -> None:
        """One draw of a pass: the colour pass from the colour lists, the depth pass from the shadow
        lists of `cascade`."""
        vao = self._vao(draw, kind, skinned, cascade if self.gpu is None else 0, index)
        if draw.morph and "u_morph_vertex_base" in vao.program:
            vao.program["u_morph_vertex_base"] = draw.morph_base
        if self.feedback is not None:
            self.feedback.draw(vao, index, cascade if kind == "depth" else None)
        elif self.gpu is not None:
            commands = self.gpu.shadow_commands if kind == "depth" else self.gpu.commands
            vao.render_indirect(commands, moderngl.TRIANGLES, count=1, first=index + (cascade * len(self.draws) if kind == "depth" else 0))
        else:
            count = draw.shadow_counts[cascade] if kind == "depth" else draw.count
            if count:
                vao.render(moderngl.TRIANGLES, instances=count)

    def light_cascades(self, camera: Camera, instances: Instances | None = None) -> Cascades:
        """The sun's shadow cascades for this camera (crowd.draw.shadows), over ``crowd_box`` where the
        pipeline set it (the AI's world), else over the box `instances` stand in."""
        box = self.crowd_box
        some = instances is not None and len(instances) > 0
        if box is None:
            pos = instances.position if some else np.zeros((1, 3))
            box = (pos.min(axis=0), pos.max(axis=0))
        top = float(np.max(self.bounds[:, 1] + self.bounds[:, 3])) * (float(np.max(instances.scale)) if some else 1.0)
        lo, hi = np.asarray(box[0], np.float64).copy(), np.asarray(box[1], np.float64).copy()
        hi[1] = max(hi[1], lo[1] + top)  # as tall as an agent's bound
        return cascades(camera, self.sun_dir, (lo, hi), self.shadow_size, LIGHTING["u_fog_density"])

    def shadow_tiles(self, view: "FrameView"):
        """(cascade, light matrix) for each cascade, the shadow framebuffer's viewport on its tile."""
        for k, matrix in enumerate(view.shadow.view_proj):
            self._shadow_fbo.viewport = (k * self.shadow_size, 0, self.shadow_size, self.shadow_size)
            yield k, matrix

    def shadow_pass(self, view: "FrameView", processor) -> bool:
        if not self.shadows:
            return False
        self._shadow_fbo.use()
        self._shadow_fbo.viewport = (0, 0, *self.shadow_map.size)
        self._shadow_fbo.clear(depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        for k, matrix in self.shadow_tiles(view):
            for layout, morph in self._variants():
                prog = self._program("depth", True, layout, morph)
                processor.bind_palette(0, prog)
                if morph:
                    self.morph.bind(prog)
                prog["u_view_proj"].write(gl_bytes(matrix))
                if layout == "" and self.merged:
                    self._render_merged("depth", True, k, morph)
                    continue
                if layout == "impostor":
                    prog["u_toward_light"] = tuple(float(x) for x in self.sun_dir)
                for index, draw in enumerate(self.draws):
                    if (draw.layout, draw.morph) == (layout, morph):
                        if layout == "impostor":
                            self._bind_piece(draw, prog)
                        self._render(index, draw, "depth", True, k)
        return True

    def set_lighting(self, prog, view: "FrameView"):
        for name, value in LIGHTING.items():
            if name in prog:
                prog[name] = value
        if self.shadows and "u_light_view_proj" in prog:
            prog["u_light_view_proj"].write(b"".join(gl_bytes(m) for m in view.shadow.view_proj))
            prog["u_shadow_texel"].write(view.shadow.texel_m.tobytes())
            prog["u_shadow_bias"].write(view.shadow.depth_bias.tobytes())
            self.shadow_map.use(3)

    def color_pass(self, framebuffer, view: "FrameView", processor, skinned: bool = True) -> None:
        framebuffer.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        try:
            # (The unskinned benchmark ceiling reads no palette, so no pairs: its pieces draw without morphs.)
            for layout, morph in sorted({(layout, morph and skinned is True) for layout, morph in self._variants()}):
                prog = self._program("color", skinned, layout, morph)
                if skinned:
                    processor.bind_palette(0, prog)
                if morph:
                    self.morph.bind(prog)
                prog["u_view_proj"].write(gl_bytes(view.view_proj))
                self.set_lighting(prog, view)
                if layout == "" and self.merged:
                    self._render_merged("color", skinned, morph=morph)
                    continue
                for index, draw in enumerate(self.draws):
                    if (draw.layout, draw.morph and skinned is True) == (layout, morph) and (draw.count or self.culls_on_gpu):
                        if layout == "impostor" and skinned is not True:  # the unskinned ceiling binds no palette, so no keys
                            continue
                        self._bind_piece(draw, prog)
                        self._render(index, draw, "color", skinned)
        finally:
            if self.materials is not None:  # a sampler object left on its unit would override what binds there next
                self.materials.unbind()

    def _bind_piece(self, draw: _Draw, prog: moderngl.Program) -> None:
        """What one draw's program reads besides the palette and its lists: an impostor's atlas and key
        offset, or a textured piece's texture layer (and coordinate box where packed)."""
        if draw.layout == "impostor":
            self.impostors[draw.character].bind(prog, self.palette.parts[draw.character].slots)
            return
        if draw.layout:
            self.materials.bind(draw.texture, prog)
        if draw.layout == "packed":
            prog["u_uv_box"] = draw.uv_box

    def bake_pass(self, framebuffer, processor, boxes: moderngl.Texture, uniforms: dict) -> None:
        """The impostor bake's draw of one view (crowd.draw.impostors.bake_atlas): every prepared agent
        (the CPU path's lists, in agent order: instance t is frame t) into its cell, through the
        IMPOSTOR_BAKE programs; `boxes` the per-frame box texture, `uniforms` the view's."""
        framebuffer.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
        boxes.use(BAKE_BOXES_UNIT)
        try:
            for layout, _ in self._variants():
                prog = self._program("bake", True, layout)
                processor.bind_palette(0, prog)
                prog["u_bake_boxes"] = BAKE_BOXES_UNIT
                for name, value in uniforms.items():
                    if name in prog:
                        prog[name] = tuple(float(x) for x in value) if isinstance(value, np.ndarray) else value
                for index, draw in enumerate(self.draws):
                    if draw.layout == layout and draw.count:
                        self._bind_piece(draw, prog)
                        self._render(index, draw, "bake", True)
        finally:
            if self.materials is not None:
                self.materials.unbind()

    def ground_pass(self, framebuffer, view: "FrameView") -> None:
        framebuffer.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        prog = self._program("ground", False)
        prog["u_view_proj"].write(gl_bytes(view.view_proj))
        eye = np.asarray(view.camera.eye, np.float64)
        period = TILE if self.town else 1000.0  # (a whole number of metres: the 1 m grid stays where it is)
        prog["u_eye"] = (float(np.mod(eye[0], period)), float(eye[1]), float(np.mod(eye[2], period)))
        self.set_lighting(prog, view)
        self._ground_vao.render(moderngl.TRIANGLES)


def _read_by(prog: moderngl.Program, layout: tuple) -> tuple:
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
            spec.append(item if next(named) in prog else _padding(item))
    return (" ".join(spec) + ("/i" if per_instance else ""), *[n for n in names if n in prog])


def _padding(fmt: str) -> str:
    """A format item's bytes as padding, for attributes a program variant does not read."""
    count = int(fmt[0]) if fmt[0].isdigit() else 1
    kind = fmt[1:] if fmt[0].isdigit() else fmt
    size = {"f": 4, "u": 4, "i": 4, "f1": 1, "u1": 1, "f2": 2, "u2": 2, "f4": 4, "u4": 4}[kind]
    return f"{count * size}x"
