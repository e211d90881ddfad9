"""Render stage: skinned instanced draws of the crowd, its shadow pass, and the ground.

Contract: ``CrowdRenderer.prepare(camera, instances, row_offset) -> FrameView``, then the passes, each given that view.
- ``instances`` (``Instances``): per agent a float64 world position, heading, scale, tint and, for
  each variation group ("head"), which piece it wears. Agent i's palette row is row i.
- The processor must have written this frame's palette; every pass here only reads it.
- Every agent's 32-byte record is packed and written once a frame (crowd.draw.records); one instanced draw
  per (mesh piece, LOD) draws the agents of its list (crowd.draw.cull_lists: one list per character, LOD
  and variation choice, shared by every piece worn there), each instance a 4-byte entry naming its agent.
  Three cull paths fill the lists behind this one interface: "cpu", numpy (any GL 3.3 context,
  crowd/draw/cpu_cull.py); "gpu" (GL 4.3, crowd/draw/gpu_cull.py), a compute pass compacting every pass's
  lists into one buffer and writing the indirect commands the passes draw with; and "feedback" (GL 4.0 to
  4.2: macOS, crowd/draw/feedback_cull.py), the same decisions made by transform-feedback draws and drawn
  with glDrawElementsIndirect.
- Positions are camera-relative: the CPU subtracts the camera in float64 and the GPU only sees small
  float32 numbers, so agents 1e5 m from the origin do not jitter.
- With shadows on, a depth pass draws each of the sun's cascades (crowd/draw/shadows.py) into its tile
  of one shadow map, from lists of its own, culled against that cascade's box one LOD coarser, with the
  same palette rows (process once, use in every pass). With shadows off, neither the shadow map nor the
  shadow lists exist.
- With occlusion on (the gpu path), the colour cull also drops agents hidden in the previous frame's
  depth pyramid (crowd/draw/occlusion.py), which ``capture_depth`` builds after the colour passes.
- Morph targets: a piece whose character's targets the scene moves is drawn by the MORPH program. On
  the gpu path each such draw has a plain twin, and the cull (given the processor: ``prepare(...,
  processor=)``) lists there the agents whose weights move nothing, so they cost what they would
  without morphs; the cpu and feedback paths draw every agent of a morph piece with the MORPH program.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import moderngl
import numpy as np

from ..errors import CrowdError
from ..anim.palette_layout import PaletteLayout
from ..asset.lod import REFERENCE_FOV_Y, REFERENCE_HEIGHT_PX
from ..asset.model import Character
from ..asset.town import TILE
from ..asset.vertex_cache import best_triangle_order
from ..frame import Camera, Instances, SimFrame
from ..gl import GLStage, gpu_bytes, has_compute, has_uniform, set_uniforms
from ..lighting import FOG_COLOR, SUN_DIR, fog_density
from ..settings import DEFAULTS, SETTINGS
from .cpu_cull import CpuCull
from .cull_lists import ALL, MOVING, STILL, DrawSpec, ListError, ListPlan
from .feedback_cull import FeedbackCull, FeedbackCullError
from .gpu_records import GpuRecordPass
from .gpu_cull import CullCharacter, GpuCull, GpuCullError
from .impostors import BLEND_PX, HELD_GROUP, HELD_NONE, ImpostorTextures, held_pieces
from .materials import MaterialTextures
from .morph import MorphDeltas
from .occlusion import DepthPyramid
from .packing import LAYOUTS, pack_vertices, read_by, shared_buffers, uv_box, uv_layout
from .records import AgentRecords, RecordError, RecordPacker
from .shadows import CASCADES, Cascades
from .splat import HELD_PX, SPLAT_PX, ImpostorSplat
from .draw_programs import draw_program, lighting_defines
from .frame_block import FrameBlock
from .drawn_counts import DrawnCounts
from .view import CascadeCache, FrameView, focal_px, frustum_planes, gl_bytes, view_proj

IMPOSTOR_PIECE = "impostor"  # the piece name of a character's impostor draw (crowd.draw.impostors)
ENTRY_FORMAT = ("1u/i", "i_entry")  # a list's entries, one an instance (shaders/agent_instance.glsl)
CULL_PATHS = ("cpu", "gpu", "feedback")
BAKE_BOXES_UNIT = 4  # the impostor bake's per-frame boxes (the palette takes 0-2, the shadow map 3)
DEFAULT_LOD_DISTANCES = DEFAULTS["lod_distances"]  # metres: LOD0 closer than the first, LOD1 to the second, LOD2 beyond


class RenderError(CrowdError, ValueError):
    """Bad render input; the message is one line."""


@dataclass
class _Draw:
    piece: str
    lod: int
    triangles: int
    vbo: moderngl.Buffer | None  # None: in the GPU path's shared buffers (first_index, base_vertex)
    ibo: moderngl.Buffer | None
    texture: int = -1  # index into the cast's textures, -1: none
    layout: str = ""  # uv_layout
    uv_box: tuple = (0.0, 0.0, 1.0, 1.0)  # corner and size of the texture coordinates' unorm16 box
    vaos: dict = field(default_factory=dict)  # (kind, skinned, pass) -> VertexArray
    count: int = 0  # instances in the view's pass (the GPU paths: as the newest counts read back say)
    shadow_counts: list = field(default_factory=list)  # instances in each cascade's pass
    first_index: int = 0
    base_vertex: int = 0
    character: int = 0  # whose piece it is: the cast's index
    group: int = -1  # its variation group (an index into group_names), -1: worn by every agent
    choice: int = 0  # its place among its group's pieces
    morph: bool = False  # drawn with its morph targets (crowd.draw.morph)
    morph_base: int = 0  # the morph vertex table's index of its gl_VertexID 0
    twin_of: "_Draw | None" = None  # the GPU path's plain twin of this morph draw


class CrowdRenderer(DrawnCounts, GLStage):
    """Owns the meshes, the agent records, the cull of its path, the programs, the shadow map and the ground
    of the crowd view."""

    def __init__(self, ctx: moderngl.Context, characters, pieces: tuple[str, ...] | None = None, lod_distances=DEFAULT_LOD_DISTANCES,
                 shadows: bool = True, shadow_size: int = 2048, culling: bool = True, cull_path: str = "cpu",
                 weapons_visibility: bool = False, occlusion: bool = False, town: bool = False, morphs=None, morph_buffers: bool | None = None,
                 impostors=None, impostor_distance: float = math.inf, lod_fade: float = 0.0, lod_error_px: float = DEFAULTS["lod_error_px"],
                 splat_px: float | None = None):
        """`characters`: one Character, or the cast's, in its order (its agents come in that order,
        crowd.frame). `cull_path`: "cpu", "gpu" (a GL 4.3 context) or "feedback" (GL 4.0; see the module docstring); with
        `weapons_visibility` the GPU culls also write each agent's visibility, for the weapons; with
        `occlusion` (the gpu path) it also drops agents hidden in the previous frame's depth. `morphs`: per
        character, whether the scene moves its morph targets (its bake has morph tracks: the processor then
        writes its agents' pairs); its pieces with targets are drawn with them, their deltas in storage
        buffers (`morph_buffers`; None: where the context has GL 4.3) or textures. `impostors`: per character,
        its ImpostorAtlas (crowd.draw.impostors) or None; an agent of a character with one is drawn as its
        impostor from `impostor_distance` metres on (its last LOD; its processor row starts with its key).
        `lod_fade`: metres past each LOD switch (the impostor's too) over which an agent is drawn at both
        LODs, cross-faded by a dither (shaders/lod_fade.glsl); 0, none. `lod_error_px`: a character with
        generated LODs (its own `lod_distances`, each where its error is one pixel) switches where the error covers this many.
        `splat_px`: on the gpu cull path, impostors shorter than this many pixels are drawn by compute passes
        instead of quads (crowd.draw.splat; 0: never; None: SPLAT_PX)."""
        self._objects: dict[str, list] = {"meshes": [], "records": [], "programs": [], "shadow_map": [], "ground": [], "textures": [], "cull": [],
                                          "occlusion": [], "morphs": [], "impostors": [], "splat": [], "frame": []}
        self.pyramid: DepthPyramid | None = None
        self.splat: ImpostorSplat | None = None
        self._view_height = 0  # the view's height, pixels (0: not known yet: the reference view's)
        self._view_scale = 1.0  # its pixels a metre against the reference view's (crowd.asset.lod)
        self._programs: dict[tuple, moderngl.Program] = {}
        self.draws: list[_Draw] = []
        self.materials: MaterialTextures | None = None
        self.gpu: GpuCull | None = None
        self.feedback: FeedbackCull | None = None
        self.cpu: CpuCull | None = None
        if cull_path not in CULL_PATHS:
            raise RenderError(f"cull path must be one of {', '.join(CULL_PATHS)}, got {cull_path!r}")
        self.cull_path = cull_path
        self.ctx = ctx
        self.town = town  # the ground shows the town's streets, sidewalks and lots (crowd.asset.town)
        self.culling = culling
        self._lod_distances = SETTINGS["lod_distances"].check(tuple(lod_distances), RenderError)
        self.lod_error_px = SETTINGS["lod_error_px"].check(lod_error_px, RenderError)
        cast = [characters] if isinstance(characters, Character) else list(characters)
        self.cast = cast
        self.morphs = tuple(bool(x) for x in (morphs if morphs is not None else [False] * len(cast)))
        if len(self.morphs) != len(cast):
            raise RenderError(f"morphs must say for each of the {len(cast)} characters whether its targets move, got {len(self.morphs)}")
        self.morph: MorphDeltas | None = None
        self.morph_buffers = has_compute(ctx) if morph_buffers is None else bool(morph_buffers)
        per_character = [[m for m in c.meshes if pieces is None or m.piece in pieces] for c in cast]
        # KHR_materials_unlit: the colour programs read each vertex's flag only where some piece is unlit
        # (the held weapons' too: set below), and a character's impostor is unlit where all its pieces are
        # (its atlas holds no flag).
        self.unlit_impostor = [bool(meshes) and all(m.unlit for m in meshes) for meshes in per_character]
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
        self.unlit_pieces = any(m.unlit for meshes in per_character for m in meshes)
        # Variation groups, per character (group -> its pieces, in order), and every group any has, in
        # the order met (an agent's choice in each is a field of its record: crowd.draw.cull_lists).
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
        self._held_group = self.group_names.index(HELD_GROUP) if HELD_GROUP in self.group_names else -1  # (the cull's, for HELD_PX)
        self._build_draws(ctx, per_character, atlases)
        self.shadows = shadows
        for draw in self.draws if shadows else ():
            draw.shadow_counts = [0] * CASCADES
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
        self._build_cull(weapons_visibility)
        splat_px = SPLAT_PX if splat_px is None else splat_px
        if not 0.0 <= float(splat_px) <= BLEND_PX:  # (the splat shows the nearest cell, as quads do below BLEND_PX)
            raise RenderError(f"the splat height must be 0 to {BLEND_PX:g} pixels, got {splat_px}")
        self.splat_px = float(splat_px)
        if self.splat_px > 0.0 and self.gpu is not None and any(d.layout == "impostor" for d in self.draws):
            unlit = [self.unlit_impostor[d.character] for d in self.draws if d.layout == "impostor"]  # (in the draws' order)
            self.splat = self._own("splat", ImpostorSplat(ctx, lighting_defines(self.shadows), unlit))
        self.shadow_size = int(shadow_size)
        self.shadow_map = None
        self._shadow_fbo = None
        if shadows:  # one tile per cascade, side by side (crowd.draw.shadows)
            self.shadow_map = self._own("shadow_map", ctx.depth_texture((CASCADES * self.shadow_size, self.shadow_size)))
            self.shadow_map.compare_func = "<="
            self.shadow_map.filter = (moderngl.LINEAR, moderngl.LINEAR)
            self.shadow_map.repeat_x = self.shadow_map.repeat_y = False
            self._shadow_fbo = self._own("shadow_map", ctx.framebuffer(depth_attachment=self.shadow_map))
        self.frame_block = self._own("frame", FrameBlock(ctx))  # the camera and the light, once a frame
        ground_prog = self._program("ground", False)
        extent = 20_000.0  # past any crowd's far side: a million agents stand 2.4 km wide (the fog hides the edge)
        quad = np.array([[-extent, -extent], [extent, -extent], [extent, extent], [-extent, -extent], [extent, extent], [-extent, extent]], np.float32)
        self._ground_vbo = self._own("ground", ctx.buffer(quad.tobytes()))
        self._ground_vao = self._own("ground", ctx.vertex_array(ground_prog, [(self._ground_vbo, "2f", "in_position")]))
        self.sun_dir = np.array(SUN_DIR)
        self.crowd_box: tuple[np.ndarray, np.ndarray] | None = None  # world (lo, hi) the agents stand in; None: measured each frame
        self.set_occlusion(occlusion)
        self.palette: PaletteLayout | None = None
        self._pending = None
        self._last = {"triangles": 0, "instances": 0, "visible": 0, "draws": 0, "lod_counts": [0] * self.lod_count, "shadow_instances": 0,
                      "cast_visible": [0] * len(self.cast), "impostors": 0}
        self._counts_due = False  # the GPU paths' counts are read when ``last`` is, not every frame
        self._light = CascadeCache()

    def _build_draws(self, ctx: moderngl.Context, per_character: list, atlases: list) -> None:
        """One draw per (piece, LOD) of every character, its mesh packed; on the GPU path the untextured ones
        share buffers (draws 0 .. merged - 1) and each morph draw has a plain twin; then the impostors."""
        cast = self.cast
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
            group, choice = self._place(k, m.piece, m.group)
            if morphing(k, m):
                morph_meshes.append((m, len(cast[k].morphs)))
            if self.cull_path == "gpu" and m.texture < 0:
                shared.append((vertices, indices))
                self.draws.append(_Draw(m.piece, m.lod, m.triangle_count, None, None, texture, "", box, character=k, group=group, choice=choice,
                                        morph=morphing(k, m)))
                continue
            vbo = self._own("meshes", ctx.buffer(vertices.tobytes()))
            ibo = self._own("meshes", ctx.buffer(indices.tobytes()))
            self.draws.append(_Draw(m.piece, m.lod, m.triangle_count, vbo, ibo, texture, uv_layout(m), box, character=k, group=group, choice=choice,
                                    morph=morphing(k, m)))
        # The GPU path's untextured draws (draws 0 .. merged - 1): one vertex and one index buffer, so a pass
        # draws them all with one glMultiDrawElementsIndirect instead of a call each (each costs the CPU a
        # call through moderngl and the driver).
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
        if self.cull_path == "gpu" and morph_meshes:
            # Each morph draw's plain twin: the same geometry drawn by the program without morph code, for
            # the agents whose weights move nothing (the GPU cull routes them), so that they cost what
            # they would without morphs. The merged twins join the plain multi-draw.
            twin = lambda d: replace(d, morph=False, twin_of=d, vaos={})  # noqa: E731
            merged_twins = [twin(d) for d in self.draws[:self.merged] if d.morph]
            self.draws[self.merged_plain:self.merged_plain] = merged_twins
            self.draws += [twin(d) for d in self.draws[self.merged + len(merged_twins):] if d.morph]
            self.merged += len(merged_twins)
            self.merged_plain += len(merged_twins)
        # One quad draw per character with an atlas, after every mesh draw; its textures and the quad are
        # the "impostors" group's.
        self.impostors: list = [None] * len(cast)
        if any(a is not None for a in atlases):
            quad = self._own("impostors", ctx.buffer(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32).tobytes()))
            quad_indices = self._own("impostors", ctx.buffer(np.array([0, 1, 2, 0, 2, 3], np.uint32).tobytes()))
            for k, atlas in enumerate(atlases):
                if atlas is None:
                    continue
                self.impostors[k] = self._own("impostors", ImpostorTextures(ctx, atlas))
                self.draws.append(_Draw(IMPOSTOR_PIECE, self.impostor_lods[k], 2, quad, quad_indices, -1, "impostor", character=k))
        self._merged_vaos: dict = {}

    def _place(self, character: int, piece: str, group: str) -> tuple[int, int]:
        """(group index, choice) of a character's piece: (-1, 0) for one every agent wears."""
        if not group:
            return -1, 0
        return self.group_names.index(group), self.groups[character][group].index(piece)

    def _cull_characters(self) -> list[CullCharacter]:
        routed = {d.character for d in self.draws if d.twin_of is not None}
        return [CullCharacter(tuple(float(x) for x in self.bounds[k]), self.character_lod_distances(k),
                              self.impostor_distance if self.impostor_lods[k] >= 0 else math.inf, k in routed) for k in range(len(self.cast))]

    def _build_cull(self, weapons_visibility: bool) -> None:
        """The lists every draw reads (crowd.draw.cull_lists), the agent records, and the cull of this path."""
        twins = {id(d.twin_of) for d in self.draws if d.twin_of is not None}
        specs = [DrawSpec(d.character, d.lod, d.group, d.choice, STILL if d.twin_of is not None else MOVING if id(d) in twins else ALL)
                 for d in self.draws]
        group_choices = [[len(g.get(name, ())) for name in self.group_names] for g in self.groups]
        try:
            self.plan = ListPlan.build(specs, group_choices, self.lod_counts, [lod >= 0 for lod in self.impostor_lods])
        except ListError as exc:
            raise RenderError(str(exc)) from None
        self.records = self._own("records", AgentRecords(self.ctx))
        self._packer = RecordPacker(self.plan, self.group_names)
        self.gpu_record_pass: GpuRecordPass | None = None  # records packed from a crowd on the GPU (gpu_records)
        characters = self._cull_characters()
        cascades = CASCADES if self.shadows else 0
        try:
            if self.cull_path == "gpu":
                self.gpu = self._own("cull", GpuCull(self.ctx, self.plan, [(d.triangles * 3, d.first_index, d.base_vertex) for d in self.draws],
                                                     characters, self.records.buffer, weapons_visibility, cascades))
            elif self.cull_path == "feedback":
                self.feedback = self._own("cull", FeedbackCull(self.ctx, self.plan, [d.triangles * 3 for d in self.draws], characters,
                                                               self.records, cascades, weapons_visibility))
            else:
                self.cpu = self._own("cull", CpuCull(self.ctx, self.plan, characters, cascades, self.group_names))
        except (GpuCullError, FeedbackCullError) as exc:
            raise RenderError(f"{exc} (the cpu cull path has no such limit)") from None
        self._cull = self.gpu or self.feedback or self.cpu
        self._cull.lod_fade = self.lod_fade

    def _entries(self, index: int, cascade: int | None) -> moderngl.Buffer:
        """The buffer draw `index` reads its entries from in the view's pass or `cascade`'s."""
        if self.gpu is not None:
            return self.gpu.entries
        if self.feedback is not None:
            return self.feedback.list_buffer(index, cascade)
        return self.cpu.buffer(index, cascade)

    def _own(self, group, obj):
        self._objects[group].append(obj)
        return obj

    def _program(self, kind: str, skinned: bool | str, layout: str = "", morph: bool = False, character: int = -1) -> moderngl.Program:
        """kind: color, depth or ground; skinned: True, or False for the benchmark's unskinned ceiling;
        layout: a textured piece's vertex layout ("packed" or "wide", see uv_layout), "" for none; morph:
        pieces drawn with their morph targets."""
        key = (kind, skinned, layout, morph, character)
        if key in self._programs:
            return self._programs[key]
        unlit = self.unlit_impostor[character] if layout == "impostor" else self.unlit_pieces
        prog = draw_program(self.ctx, kind, skinned, layout, morph, shadows=self.shadows, lod_fade=self.lod_fade > 0.0, town=self.town,
                            morph_buffers=self.morph_buffers, unlit=unlit)
        self._programs[key] = self._own("programs", prog)
        return prog

    def _merged_vao(self, kind: str, skinned: bool, morph: bool = False) -> moderngl.VertexArray:
        """The GPU path's vertex array over the untextured pieces' shared buffers and the entries (for the
        program of the pieces drawn without, or with, morph targets)."""
        key = (kind, skinned, morph)
        if key not in self._merged_vaos:
            prog = self._program(kind, skinned, "", morph)
            vbo, ibo = self._merged_buffers
            content = [(vbo, *read_by(prog, LAYOUTS[""][1])), (self.gpu.entries, *read_by(prog, ENTRY_FORMAT))]
            self._merged_vaos[key] = self._own("programs", self.ctx.vertex_array(prog, content, index_buffer=ibo, index_element_size=4))
        return self._merged_vaos[key]

    def _render_merged(self, kind: str, skinned: bool, cascade: int = 0, morph: bool = False) -> None:
        """The untextured draws of a pass drawn without (or with) morph targets in one multi-draw: their
        commands are 0 .. merged_plain - 1 (merged_plain .. merged - 1) of the pass's. Unskinned (the
        benchmark's ceiling, which reads no palette) they are all one multi-draw."""
        first, count = (self.merged_plain, self.merged - self.merged_plain) if morph else (0, self.merged_plain if skinned else self.merged)
        if not count:
            return
        vao = self._merged_vao(kind, skinned, morph)
        if morph:
            vao.program["u_morph_vertex_base"] = self.draws[first].morph_base
        pass_index = 1 + cascade if kind == "depth" else 0
        vao.render_indirect(self.gpu.commands, moderngl.TRIANGLES, count=count, first=first + pass_index * len(self.draws))

    def _vao(self, draw: _Draw, kind: str, skinned: bool, cascade: int = 0, index: int = 0) -> moderngl.VertexArray:
        """Draw `index`'s vertex array for a pass: its mesh and the entries it reads there (the shadow pass:
        `cascade`'s; the GPU path's: every pass's in one buffer, by baseInstance)."""
        shadow = kind == "depth"
        key = (kind, skinned, cascade if shadow and self.gpu is None else 0)
        if key not in draw.vaos:
            prog = self._draw_program(draw, kind, skinned)
            entries = self._entries(index, cascade if shadow else None)
            content = [(draw.vbo, *read_by(prog, LAYOUTS[draw.layout][1])), (entries, *read_by(prog, ENTRY_FORMAT))]
            draw.vaos[key] = self._own("programs", self.ctx.vertex_array(prog, content, index_buffer=draw.ibo, index_element_size=4))
        return draw.vaos[key]

    def _variants(self) -> list[tuple[str, bool]]:
        """The program variants a pass runs: one per (vertex layout, drawn with morph targets) among the pieces."""
        return sorted({(d.layout, d.morph) for d in self.draws})

    def _draw_program(self, draw: _Draw, kind: str, skinned: bool) -> moderngl.Program:
        return self._program(kind, skinned, draw.layout, draw.morph and skinned is True, draw.character if draw.layout == "impostor" else -1)

    def _variant_programs(self, kind: str, skinned: bool, layout: str, morph: bool):
        """(character, program) of a variant's draws: one program for all (character None), but each
        character's impostors their own, so that its atlas's constants are written once, not at every
        switch between characters."""
        if layout != "impostor":
            return [(None, self._program(kind, skinned, layout, morph))]
        characters = sorted({d.character for d in self.draws if d.layout == "impostor"})
        return [(c, self._program(kind, skinned, layout, morph, c)) for c in characters]

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
        self._cull.lod_fade = metres

    def set_impostor_distance(self, metres: float) -> None:
        """Draw impostors from `metres` on (every cull path reads it each frame)."""
        if not float(metres) > 0.0:
            raise RenderError(f"the impostor distance must be a positive number of metres, got {metres}")
        self.impostor_distance = float(metres)
        self._cull.set_characters(self._cull_characters())

    def character_lod_distances(self, k: int) -> tuple:
        """Metres where character k's LOD 1, 2, ... start: its own (generated: where its error covers
        lod_error_px pixels of this frame's view), else the setting's."""
        own = self.cast[k].lod_distances
        return tuple(float(d) * self._view_scale / self.lod_error_px for d in own) if own else tuple(self._lod_distances)

    def set_view_height(self, pixels: int) -> None:
        """The height of the view the next frames are drawn into (the colour pass says it too, a frame late)."""
        self._view_height = int(pixels)

    def _follow_view(self, fov_y: float) -> None:
        """Generated LODs switch where their error covers lod_error_px pixels of this view: their distances,
        made for the reference view (crowd.asset.lod), scaled by its pixels a metre against the reference's."""
        scale = 1.0
        if self._view_height > 0:
            scale = focal_px(self._view_height, fov_y) / focal_px(REFERENCE_HEIGHT_PX, REFERENCE_FOV_Y)
        if scale != self._view_scale:
            self._view_scale = scale
            if any(c.lod_distances for c in self.cast):
                self._cull.set_characters(self._cull_characters())

    def set_lod_error_px(self, pixels: float) -> None:
        self.lod_error_px = SETTINGS["lod_error_px"].check(pixels, RenderError)
        self._cull.set_characters(self._cull_characters())

    @property
    def lod_distances(self) -> tuple:
        """Metres from the camera where LOD 1, 2, ... start."""
        return self._lod_distances

    @lod_distances.setter
    def lod_distances(self, distances) -> None:
        self._lod_distances = SETTINGS["lod_distances"].check(tuple(distances), RenderError)
        self._cull.set_characters(self._cull_characters())

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
        """Bytes by group; "lists" is every pass's entries, "records" the agents' records."""
        out = {group: gpu_bytes(objs) for group, objs in self._objects.items() if group not in ("programs", "textures", "cull", "occlusion", "records")}
        if self.materials is not None:
            out["textures"] = self.materials.gpu_bytes()
        out["records"] = self.records.gpu_bytes()
        out["lists"] = self._cull.entry_bytes()
        if self.culls_on_gpu:  # the GPU cull's counters, commands, tables, visibility and rings
            out["cull"] = self._cull.gpu_bytes() - out["lists"]
        if self.pyramid is not None:
            out["occlusion"] = self.pyramid.gpu_bytes()
        out["morphs"] = 0 if self.morph is None else self.morph.nbytes
        out["impostors"] = gpu_bytes(self._objects["impostors"]) + sum(t.gpu_bytes() for t in self.impostors if t is not None)
        out["splat"] = 0 if self.splat is None else self.splat.gpu_bytes()
        out["frame"] = self.frame_block.gpu_bytes()
        return out

    def release(self) -> None:
        for objs in self._objects.values():
            for obj in reversed(objs):
                obj.release()
        self._objects = {k: [] for k in self._objects}
        self._programs.clear()
        self.draws = []
        self.materials = None
        self.gpu = self.feedback = self.cpu = self._cull = None
        self.pyramid = None
        self.morph = None

    # -- per frame

    @staticmethod
    def clear_color() -> tuple[float, float, float]:
        return tuple(c ** (1 / 2.2) for c in FOG_COLOR)

    def gpu_records(self, weapon_first: list[int]) -> None:
        """Pack records on the GPU from a crowd that lives there (crowd.frame.SimFrame), the GPU cull's
        path only; `weapon_first`: each crowd character's first weapon among the cast's."""
        if self.gpu is None:
            raise RenderError("a crowd on the GPU needs the GPU cull path (cull gpu, GL 4.3)")
        if self.gpu_record_pass is None:
            self.gpu_record_pass = self._own("records", GpuRecordPass(self.ctx, self.plan, self.group_names, weapon_first))

    def prepare(self, camera: Camera, instances: Instances | SimFrame, row_offset=0, cull_now: bool = True,
                palette: PaletteLayout | None = None, processor=None) -> "FrameView":
        """Pack and write every agent's record; cull, pick LODs and fill the lists in numpy (the CPU path), or
        leave that to the GPU's cull (``cull()``; now, unless `cull_now` is False, so a caller can time the
        GPU's part alone). Returns what every later pass of this frame receives (the view and light matrices,
        and the visible set where the CPU knows it: None on the GPU paths).
        `row_offset` (an int, or one per agent) is the first palette row of the ring slot each agent's
        palette is read from (see AnimationProcessor.row_offset); `palette` the processor's layout (None:
        the one the processor makes for these characters and counts). `processor`: the one whose palette the
        passes read, run for this frame already; on the GPU path its morph pairs send agents moving no target
        to the plain twins (None: to the morph draws)."""
        camera.validate()
        self._follow_view(camera.fov_y)
        on_gpu = isinstance(instances, SimFrame)  # a crowd that lives on the GPU: `row_offset` is (slot, latest, born limit)
        if on_gpu and self.gpu_record_pass is None:
            raise RenderError("the renderer packs no records on the GPU: call gpu_records first")
        if not on_gpu:
            instances.validate(self.groups)
        counts = instances.counts()
        if len(counts) != len(self.cast):
            raise RenderError(f"instances of {len(counts)} characters, the renderer draws {len(self.cast)}")
        matrix = view_proj(camera)
        shadow = (self.light_cascades(camera, None, instances.max_scale) if on_gpu else self.light_cascades(camera, instances)) \
            if self.shadows else None
        eye = np.asarray(camera.eye, np.float64)
        palette = palette or PaletteLayout.make([c.skeleton.joint_count for c in self.cast], counts)
        self.palette = palette  # the layout this frame's records address (tests and benchmarks read lists back by it)
        if tuple(p.morph for p in palette.parts) != self.morphs:
            raise RenderError(f"the palette holds morph pairs for characters {[p.morph for p in palette.parts]}, the draw reads them for "
                              f"{list(self.morphs)}: build both from the same bakes")
        try:
            if on_gpu:
                self.gpu_record_pass.run(instances, self.records, eye, palette, *row_offset)
            else:
                self.records.write(self._packer.pack(instances, eye, row_offset, palette))
            if self.cpu is None:
                self._cull.upload(instances.rows if on_gpu else len(instances), counts)
        except (RecordError, GpuCullError, FeedbackCullError) as exc:
            raise RenderError(f"{exc}") from None
        planes = frustum_planes(matrix)
        light = (None, None) if shadow is None else (self._light.planes(shadow), shadow.reach_m)
        if self.cpu is None:
            self._counts_due = True  # (read when ``last`` is: the newest frame the GPU has finished)
            self._pending = (planes, light, eye, camera.fov_y)
            if cull_now:
                self.cull(processor)
            return self._frame_view(FrameView(camera, matrix, shadow, None))
        picks = self.cpu.run(instances, eye, planes, self.culling, *light)
        for d, draw in enumerate(self.draws):
            draw.count = int(picks.counts[0, d])
            draw.shadow_counts = [int(c) for c in picks.counts[1:, d]]
        shown = picks.visible
        self._last = {"triangles": int(sum(d.count * d.triangles for d in self.draws)), "instances": int(picks.counts[0].sum()),
                     "visible": int(shown.sum()), "draws": int(np.count_nonzero(picks.counts[0])),
                     "lod_counts": np.bincount(picks.lod[shown], minlength=self.lod_count).tolist(),
                     "shadow_instances": int(picks.counts[1:].sum()), "cast_visible": picks.cast_visible,
                     "impostors": picks.impostors}
        return self._frame_view(FrameView(camera, matrix, shadow, picks.visible, picks.casting, picks.lod, picks.held))

    def _frame_view(self, view: "FrameView") -> "FrameView":
        """`view`, its camera and light written to the frame block every later pass reads."""
        self.frame_block.write(view, fog_density(view.camera.fog_reach))
        return view

    def cull(self, processor=None) -> bool:
        """The GPU paths' cull for what `prepare(cull_now=False)` uploaded; False when there is nothing to do
        (the CPU path, or already done). `processor`: as for ``prepare``."""
        pending, self._pending = self._pending, None
        if not self.culls_on_gpu or pending is None:
            return False
        planes, (shadow_planes, reach), eye, fov_y = pending
        if self.feedback is not None:
            self.feedback.run(planes, self.culling, shadow_planes, reach)
        else:
            # Impostors under HELD_PX hold no weapon in the view (crowd.draw.splat), at the view's height (set_view_height).
            self.gpu.run(planes, self.culling, shadow_planes, reach, occlusion=None if self.pyramid is None else (self.pyramid, eye),
                         palette=processor, held=(self._held_group, focal_px(self._view_height, fov_y), HELD_PX))
        return True

    @property
    def culls_on_gpu(self) -> bool:
        """Whether the lists are made on the GPU (the gpu and feedback paths), by ``cull()``."""
        return self.gpu is not None or self.feedback is not None

    def draws_anything(self, agents: int) -> bool:
        """Whether this frame's passes have instances to draw (the GPU paths cannot know: any agent may be)."""
        return agents > 0 if self.culls_on_gpu else bool(self.last["instances"])

    def _render(self, index: int, draw: _Draw, kind: str, skinned: bool, cascade: int = 0) -> None:
        """One draw of a pass: the colour pass from the view's entries, the depth pass from `cascade`'s."""
        vao = self._vao(draw, kind, skinned, cascade, index)
        if draw.morph and has_uniform(vao.program, "u_morph_vertex_base"):
            vao.program["u_morph_vertex_base"] = draw.morph_base
        if self.feedback is not None:
            self.feedback.draw(vao, index, cascade if kind == "depth" else None)
        elif self.gpu is not None:
            pass_index = 1 + cascade if kind == "depth" else 0
            vao.render_indirect(self.gpu.commands, moderngl.TRIANGLES, count=1, first=index + pass_index * len(self.draws))
        else:
            count = draw.shadow_counts[cascade] if kind == "depth" else draw.count
            if count:
                vao.render(moderngl.TRIANGLES, instances=count)

    def light_cascades(self, camera: Camera, instances: Instances | None = None, max_scale: float | None = None) -> Cascades:
        """The sun's shadow cascades for this camera (crowd.draw.shadows), over ``crowd_box`` where the
        pipeline set it (the AI's world), else over the box `instances` stand in; `max_scale`: the
        largest agent scale, where no instances say it."""
        box = self.crowd_box
        some = instances is not None and len(instances) > 0
        if box is None:
            pos = instances.position if some else np.zeros((1, 3))
            box = (pos.min(axis=0), pos.max(axis=0))
        scale = max_scale if max_scale is not None else float(np.max(instances.scale)) if some else 1.0
        top = float(np.max(self.bounds[:, 1] + self.bounds[:, 3])) * scale
        lo, hi = np.asarray(box[0], np.float64).copy(), np.asarray(box[1], np.float64).copy()
        hi[1] = max(hi[1], lo[1] + top)  # as tall as an agent's bound
        return self._light.cascades(camera, self.sun_dir, (lo, hi), self.shadow_size, fog_density(camera.fog_reach))

    def shadow_tiles(self, view: "FrameView"):
        """(cascade, light matrix) for each cascade, the shadow framebuffer's viewport on its tile."""
        for k, matrix in enumerate(view.shadow.view_proj):
            self._shadow_fbo.viewport = (k * self.shadow_size, 0, self.shadow_size, self.shadow_size)
            yield k, matrix

    def shadow_pass(self, view: "FrameView", processor) -> bool:
        if not self.shadows:
            return False
        self.records.bind()
        self._shadow_fbo.use()
        self._shadow_fbo.viewport = (0, 0, *self.shadow_map.size)
        self._shadow_fbo.clear(depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        toward = tuple(float(x) for x in self.sun_dir)
        for k, matrix in self.shadow_tiles(view):
            matrix = gl_bytes(matrix)
            for layout, morph in self._variants():
                for character, prog in self._variant_programs("depth", True, layout, morph):
                    processor.bind_palette(0, prog)
                    if morph:
                        self.morph.bind(prog)
                    set_uniforms(prog, u_view_proj=matrix)
                    if layout == "" and self.merged:
                        self._render_merged("depth", True, k, morph)
                        continue
                    if layout == "impostor":
                        set_uniforms(prog, u_toward_light=toward)
                    for index, draw in enumerate(self.draws):
                        if (draw.layout, draw.morph) == (layout, morph) and character in (None, draw.character):
                            if layout == "impostor":
                                self._bind_piece(draw, prog)
                            self._render(index, draw, "depth", True, k)
        return True

    def bind_shadow_map(self) -> None:
        """The shadow map on the unit the lit programs read it from (their camera and light: the frame block)."""
        if self.shadows:
            self.shadow_map.use(3)

    def color_pass(self, framebuffer, view: "FrameView", processor, skinned: bool = True) -> None:
        self._view_height = framebuffer.viewport[3]
        self.records.bind()
        framebuffer.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        try:
            # (The unskinned benchmark ceiling reads no palette, so no pairs: its pieces draw without morphs.)
            focal = focal_px(framebuffer.viewport[3], view.camera.fov_y)
            self.bind_shadow_map()  # (the camera and the light: the frame block)
            for layout, morph in sorted({(layout, morph and skinned is True) for layout, morph in self._variants()}):
                if layout == "impostor" and skinned is not True:  # the unskinned ceiling binds no palette, so no keys
                    continue
                for character, prog in self._variant_programs("color", skinned, layout, morph):
                    if skinned:
                        processor.bind_palette(0, prog)
                    if morph:
                        self.morph.bind(prog)
                    if layout == "" and self.merged:
                        self._render_merged("color", skinned, morph=morph)
                        continue
                    if layout == "impostor":  # (an impostor's height on screen)
                        set_uniforms(prog, u_focal_px=focal)
                    for index, draw in enumerate(self.draws):
                        if (draw.layout, draw.morph and skinned is True) == (layout, morph) and (draw.count or self.culls_on_gpu) \
                                and character in (None, draw.character):
                            self._bind_piece(draw, prog)
                            self._render(index, draw, "color", skinned)
            if self.splat is not None and skinned is True:
                self.splat.resolve(framebuffer)
        finally:
            if self.materials is not None:  # a sampler object left on its unit would override what binds there next
                self.materials.unbind()

    def splat_pass(self, framebuffer, view: "FrameView", processor) -> bool:
        """The small impostors of the colour pass splatted (crowd.draw.splat), before ``color_pass`` draws
        the rest; False where the splat is off."""
        if self.splat is None:
            return False
        draws = [(index, draw.character) for index, draw in enumerate(self.draws) if draw.layout == "impostor"]  # (the view's commands come first)
        self.records.bind()
        self.splat.run(framebuffer, view, self, processor, draws, self.records.agents, self.splat_px)
        return True

    def bind_impostor(self, character: int, prog) -> None:
        """`character`'s impostor atlas and key offset for `prog`."""
        self.impostors[character].bind(prog, self.palette.parts[character].slots)

    def _bind_piece(self, draw: _Draw, prog: moderngl.Program) -> None:
        """What one draw's program reads besides the palette and its lists: an impostor's atlas and key
        offset, or a textured piece's texture layer (and coordinate box where packed)."""
        if draw.layout == "impostor":
            self.bind_impostor(draw.character, prog)
            return
        if draw.layout:
            self.materials.bind(draw.texture, prog)
        if draw.layout == "packed":
            prog["u_uv_box"] = draw.uv_box

    def bake_pass(self, framebuffer, processor, boxes: moderngl.Texture, uniforms: dict) -> None:
        """The impostor bake's draw of one view (crowd.draw.impostors.bake_atlas): every prepared agent
        (the CPU path's lists, in agent order: instance t is frame t) into its cell, through the
        IMPOSTOR_BAKE programs; `boxes` the per-frame box texture, `uniforms` the view's."""
        self.records.bind()
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
                    if has_uniform(prog, name):
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
        eye = np.asarray(view.camera.eye, np.float64)
        period = TILE if self.town else 1000.0  # (a whole number of metres: the 1 m grid stays where it is)
        prog["u_eye"] = (float(np.mod(eye[0], period)), float(eye[1]), float(np.mod(eye[2], period)))
        self.bind_shadow_map()  # (the camera and the light: the frame block)
        self._ground_vao.render(moderngl.TRIANGLES)
