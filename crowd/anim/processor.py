"""Process stage: per-agent animation layers → the FinalAnimationTexture of skinning matrices, on the GPU.

Contract (the shape of an ozz-animation job: validated inputs, documented edge cases):

input ``layers``: float32 (N, L, 4) with L = the processor's layer count (1..4); per layer
  ``[clip, phase, weight, mask]`` (column constants CLIP, PHASE, WEIGHT, MASK):
  - clip: index into the bake's clips (integer valued);
  - phase: within ±32 cycles, where float32 holds it to 1e-6 cycles (validate_layers refuses the rest,
    in one line, rather than round it); looping clips wrap it into [0, 1), one-shot clips clamp it to
    [0, 1]. Producers wrap in float64 first (crowd.sim.locomotion.advance_phase, LayerOverrides.apply);
  - weight: finite, at most MAX_WEIGHT; negative weights count as 0; weights need not sum to 1;
  - mask: -1 for the whole body, else a row of the processor's joint masks (factor per joint in [0, 1]).
  Per joint, as crowd.anim.reference.blend (its docstring says why each rule), with S the sum of the
  layers' max(weight, 0) (only ratios of weights matter): weights are multiplied by the mask; each
  layer samples its keys as the interpolation says (processor_inputs.INTERPOLATIONS: by default rotation nlerp at
  a weight corrected to track slerp, and translation lerp); rotations are sign-aligned to the anchor,
  the first-listed layer with a weight above 0 at that joint, and their weighted sum normalised (the
  anchor's rotation where the sum is shorter than CANCELLED_NORM times S), translations and scales are weighted means (dq_lerp
  instead sums the dual quaternions); a joint whose masked weights add up to less than REST_THRESHOLD
  times S takes the rest pose. Then the hierarchy is concatenated and multiplied by the inverse bind.

output: the palette, three RGBA32F array textures ("planes") holding rows 0, 1 and 2 of each 3x4
  skinning matrix. Agent a, joint j lives at texel ((a % agents_per_row) * J + j, y) of each plane,
  with y = a // agents_per_row + the ring slot's first row: one palette row per agent, several agents
  side by side in a texture row (under 4096 texels wide). Palette rows are counted across the planes'
  layers, ``layer_rows`` to a layer (shaders/palette.glsl): row y is texture row y % layer_rows of
  layer y // layer_rows. A layer is as tall as one ring slot needs, up to the driver's texture size,
  and a slot taller than that spans several layers, so a million agents fit wherever the memory does
  (a 2D texture stopped at 16,384 rows on llvmpipe: 2.9 million agents of 23 joints, or 262,000 with a
  history of 4 and 64 joints). The GL 3.3 path needs the planes: multiple render targets write the
  same pixel of several attachments, so the three texels of a joint sit at one coordinate of three
  textures. The compute path writes the same planes, so the renderers do not care which path ran.
  Readers address a texel by one code, x | y << 12 (``texel_code``), so y may reach 2^20 rows.

history: with ``history`` = H > 1 the planes hold H palettes stacked vertically (a ring): each run
  writes the next slot, and the palettes of the H - 1 runs before stay readable. The weapons' readback
  uses it to draw each body with the palette of the frame whose sockets the CPU has read
  (``row_offset(age)`` is where the palette of `age` runs ago starts). H = 1 (no weapons) keeps one.

foot lock: a processor built with ``legs`` (crowd.anim.foot_lock) holds each planted foot where it came
  down, between the blend and the composition, with a state per agent and leg that the next run reads;
  ``upload`` then also takes each agent's motion (N, 4: ground step x, z since the last run, and front x,
  z times its scale) and the frame's simulated seconds. Compute path only.

Paths: "compute" (GL 4.3, one dispatch) and "fragment" (GL 3.3, two draws: every joint's blended local
into a scratch of one ring slot's shape, then each joint's chain composed from it); "auto" takes compute
where the context has GL 4.3. Both run the same GLSL (shaders/processor_common.glsl).
"""

from __future__ import annotations

import dataclasses
import math

import moderngl
import numpy as np

from ..frame import MAX_LAYERS, validate_masks
from ..gl import GLStage, gpu_bytes, set_uniforms
from ..settings import SETTINGS
from . import foot_lock as lock
from .bake import AnimationBake
from .layer_upload import LayerUpload
from .palette_layout import MAX_PALETTE_ROWS, MAX_TEXTURE_WIDTH, PaletteLayout, palette_limits
from .processor_inputs import DEFAULT_INTERPOLATION, ProcessorError, check_history, check_interpolation, resolve_path
from .processor_programs import GROUP_SIZE, LAYERS_IN, MAX_JOINTS, CharacterPrograms, ProcessorPart, joint_mask
from .processor_readback import ProcessorReadback

# The fragment path's scratch of blended locals, read by its compose pass: three planes, a fourth (each
# joint's own non-uniform scale) where a character has one; that pass reads no u_anim_residual, so the
# fourth takes its unit.
LOCALS_UNITS = (12, 13, 14, 15)
FAR_PLACES, FAR_LOOKS = 2, 3  # processor.comp.glsl's storage bindings of the GPU crowd's places and looks (0 and 1: the foot lock's)
# Each sampler's texture unit (those a program compiled out are left out when written).
TEXTURE_UNITS = {"u_anim": 0, "u_parents": 1, "u_clips": 2, "u_layers": 3, "u_anim_scale": 4, "u_masks": 5, "u_keys": 6, "u_tracks": 7,
                 "u_morph_tracks": 8, "u_morph_clips": 9, "u_morph_variation": 10, "u_morph_held": 11,
                 **dict(zip(("u_locals0", "u_locals1", "u_locals2", "u_locals3"), LOCALS_UNITS)), "u_anim_residual": 15}

# Every name importers have found here stays importable from here, wherever it now lives.


# The character programs, the layers' upload and the read-backs live in modules of their own (processor_programs,
# layer_upload, processor_readback), mixed in here: every GL object they make or read is this class's.
class AnimationProcessor(GLStage, CharacterPrograms, LayerUpload, ProcessorReadback):
    """Owns every character's bake textures, the layers texture and the palette planes, and releases them.

    A crowd of several characters (``bakes`` a sequence) is processed one character at a time, each over
    its own range of agents (the cast's contiguous blocks, crowd.frame): a dispatch (or draw) per
    character, with that character's textures and program, into that character's block of the one
    palette (``layout``)."""

    def __init__(self, ctx: moderngl.Context, bakes, layer_count: int = MAX_LAYERS, masks=None, path: str = "auto",
                 history: int = 1, interpolation: str = DEFAULT_INTERPOLATION, legs=None, impostor_keys=None):
        """`bakes`: one AnimationBake, or one per character of the cast; `masks` and `legs` likewise (one
        value for one bake, a sequence of them for several). `impostor_keys`: per character, whether its
        agents' rows start with the key their impostors are drawn by (None: no character's do)."""
        self._own: dict[str, list] = {"animation": [], "palette": [], "layers": [], "locals": [], "processor_quad": [], "foot_lock": [], "morphs": []}
        self.parts: list[ProcessorPart] = []
        self._programs: dict[str, moderngl.Program] = {}
        single = isinstance(bakes, AnimationBake)
        bakes = [bakes] if single else list(bakes)
        masks = [masks] if single else list(masks if masks is not None else [None] * len(bakes))
        legs = [legs] if single else list(legs if legs is not None else [None] * len(bakes))
        if not bakes or len(masks) != len(bakes) or len(legs) != len(bakes):
            raise ProcessorError(f"the processor needs a bake per character, and as many masks and legs ({len(bakes)} bakes, "
                                 f"{len(masks)} masks, {len(legs)} legs)")
        SETTINGS["processor"].check(path, ProcessorError)
        if not 1 <= layer_count <= MAX_LAYERS:
            raise ProcessorError(f"layer count must be 1 to {MAX_LAYERS}, got {layer_count}")
        for bake in bakes:
            jc = bake.joint_count
            if not 1 <= jc <= MAX_JOINTS:
                raise ProcessorError(f"the processor handles 1 to {MAX_JOINTS} joints, this skeleton has {jc}")
            if np.any(bake.parents >= np.arange(jc)):
                raise ProcessorError("the hierarchy must list parents before their children")
        path = resolve_path(ctx, path)  # (refuses "compute" without GL 4.3)
        # The foot lock (crowd.anim.foot_lock): legs given and found, on the compute path, whose shared
        # memory holds an agent's locals between the blend and the composition.
        legs = [l if l is not None and len(l) else None for l in legs]
        if any(l is not None for l in legs) and path != "compute":
            raise ProcessorError("the foot lock runs on the compute path (GL 4.3); the fragment path has no state to keep it in")
        self._lock_dt = 0.0  # the simulated seconds of the frame the last upload was for
        self.ctx = ctx
        self.path = path
        self.layer_count = layer_count
        self.interpolation = check_interpolation(interpolation)
        self.history = check_history(history)
        # The layers texture's own layout: agents side by side, LAYERS texels each, whatever their skeleton.
        self.layer_agents_per_row = MAX_TEXTURE_WIDTH // layer_count
        self.runs = 0  # runs since the palette was last (re)allocated: slots older than this hold nothing
        self._far = None  # (places, looks, eye, metres, rows, joint masks): past it agents get their key alone (key_alone_beyond)
        self._far_masks = (None, [])  # (the kept joints, each character's mask of them and their ancestors)
        self.layer_rows = 1  # texture rows per layer of the planes
        self.slot_layers = 1  # layers one ring slot spans
        self.layers_texture = None  # (the fragment path's; the compute path reads a buffer)
        self._layer_unpack = None  # (the layer rows' pixel-unpack buffer, made with the texture)
        self._layer_rows = 0  # rows of layers the storage holds (LAYERS * layer_agents_per_row texels a row)
        self._layer_buffer = None  # the compute path's own layers, made at its first upload from the CPU
        self._layers_source = None  # the buffer the compute path's next run reads: its own, or upload_from's
        self._locals, self._locals_framebuffer = (), None  # (the fragment path's scratch of blended locals)
        self.planes: tuple = ()
        self._framebuffer = None
        keys = list(impostor_keys) if impostor_keys is not None else [False] * len(bakes)
        if len(keys) != len(bakes):
            raise ProcessorError(f"impostor keys for {len(keys)} characters, the processor has {len(bakes)} bakes")
        for bake, m, l, key in zip(bakes, masks, legs, keys):
            part = ProcessorPart(bake, validate_masks(m, bake.joint_count), l, key)
            self.parts.append(part)
            self._make_part(part)
        self.layout = self._layout([0] * len(self.parts))
        self.agents = 0

    # -- what the stages and tests read

    @property
    def bakes(self) -> list[AnimationBake]:
        return [p.bake for p in self.parts]

    @property
    def legs(self):
        """Each character's legs the foot lock holds (None for a character without), or None where the
        lock runs for nobody."""
        legs = tuple(p.legs for p in self.parts)
        return None if all(l is None for l in legs) else legs

    @property
    def masks(self) -> tuple:
        return tuple(p.masks for p in self.parts)

    @property
    def anim_texture(self) -> moderngl.Texture:
        """The first character's AnimationTexture (tests)."""
        return self.parts[0].textures["u_anim"]

    # -- resources

    def _texture(self, group, size, components, data, dtype):
        tex = self.ctx.texture(size, components, None if data is None else np.ascontiguousarray(data).tobytes(), dtype=dtype)
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._own[group].append(tex)
        return tex

    def _release_group(self, group):
        for obj in self._own[group]:
            obj.release()
        self._own[group] = []

    def palette_rows(self, agents=None) -> int:
        """Palette rows the agents fill (one ring slot's); `agents`: counts per character (default the current)."""
        if agents is None:
            return self.layout.rows
        return self._layout(self._counts(agents)).rows

    def slot_rows(self) -> int:
        """Palette rows from one ring slot's start to the next's: its layers' rows."""
        return self.slot_layers * self.layer_rows

    def row_offset(self, age: int = 0) -> int:
        """First palette row (counted across layers) of the palette written `age` runs ago (0: the latest run)."""
        if not 0 <= age < min(self.history, max(self.runs, 1)):
            raise ProcessorError(f"no palette from {age} runs ago (history {self.history}, {self.runs} runs since allocation)")
        return ((self.runs - 1 - age) % self.history) * self.slot_rows()

    def set_history(self, history: int) -> None:
        """Keep `history` palettes (1 to MAX_HISTORY); the planes are reallocated, so older runs are lost."""
        history = check_history(history)
        if history != self.history:
            self.history = history
            self._allocate(self.layout.counts)

    def _layout(self, counts) -> PaletteLayout:
        """The palette's layout for `counts` agents per character (each with its morph slots, if any)."""
        return PaletteLayout.make([p.bake.joint_count for p in self.parts], counts, [p.slots for p in self.parts], [p.morph for p in self.parts])

    def _counts(self, agents) -> tuple[int, ...]:
        """Agent counts per character from a count (one character) or a sequence of them, checked."""
        counts = (agents,) if isinstance(agents, (int, np.integer)) and not isinstance(agents, bool) else tuple(agents) \
            if isinstance(agents, (tuple, list)) else None
        if counts is None or len(counts) != len(self.parts) or any(
                isinstance(c, bool) or not isinstance(c, (int, np.integer)) or c < 0 for c in counts):
            raise ProcessorError(f"agent count must be a whole number >= 0 per character ({len(self.parts)} of them), got {agents!r}")
        return tuple(int(c) for c in counts)

    def resize(self, agents) -> None:
        """Make room for exactly `agents` agents (a count, or one per character); everything for agents no
        longer there is released. The agents kept (each character's first ones, crowd.frame.cast_moves)
        keep their palette history: new planes get the kept rows copied across on the GPU (so weapons
        stay in hand through it), and their foot-lock state."""
        counts = self._counts(agents)
        old = self.layout
        try:
            new = self._layout(counts)
            if new.rows == old.rows and self.planes and new.agents and all(a.first_row == b.first_row for a, b in zip(old.parts, new.parts)):
                self.layout, self.agents = new, new.agents  # the same texture rows: the agents kept keep their palette history
                if self._layer_rows != math.ceil(new.agents / self.layer_agents_per_row):
                    self._make_layers(new.agents)  # (the layers' own rows may still differ: 2,048 agents a row)
                self._update_quads()
                return
            self._allocate(counts, keep=True)
        finally:
            self._resize_lock(old.counts, self.layout.counts)

    def _resize_lock(self, old: tuple[int, ...], new: tuple[int, ...]) -> None:
        """Each character's foot-lock state (a vec4 per agent and leg) and motion (a vec4 per agent)
        buffers: its agents kept keep their state, new ones start free with nothing carried."""
        for part, agents in zip(self.parts, new):
            if part.legs is None:
                continue
            size = agents * len(part.legs) * 16
            if part.lock_state is not None and part.lock_state.size == size and agents:
                continue
            was, objects = part.lock_state, [o for o in (part.lock_state, part.lock_motion) if o is not None]
            for obj in objects:
                self._own["foot_lock"].remove(obj)
            part.lock_state = part.lock_motion = None
            try:
                if agents:
                    state = self.ctx.buffer(reserve=size)
                    self._own["foot_lock"].append(state)
                    state.clear()
                    if was is not None:
                        self.ctx.copy_buffer(state, was, size=min(size, was.size))
                    part.lock_motion = self.ctx.buffer(reserve=agents * 16)
                    self._own["foot_lock"].append(part.lock_motion)
                    part.lock_state = state
            finally:
                for obj in objects:
                    obj.release()

    def _allocate(self, counts: tuple[int, ...], keep: bool = False) -> None:
        layout = self._layout(counts)
        rows = layout.rows
        limit, max_layers = palette_limits(self.ctx)
        layer_rows = max(1, min(rows, limit))
        slot_layers = max(1, math.ceil(rows / layer_rows))
        layers = slot_layers * self.history
        width = layout.width
        agents = layout.agents
        if layers > max_layers or layers * layer_rows > MAX_PALETTE_ROWS:
            raise ProcessorError(f"{agents:,} agents with a palette history of {self.history} need {layers} palette layers of "
                                 f"{layer_rows:,} rows, more than this GPU's {max_layers} layers or the {MAX_PALETTE_ROWS:,} rows a texel code addresses")
        # The palettes kept across (`keep`, with something written and agents on both sides): the old
        # planes stay alive until they are copied; the ring's position (runs) carries over.
        old, old_objects = None, []  # (planes, their layout, layer rows and layers a slot), and what releases them
        if keep and self.planes and self.runs and agents:
            old = (self.planes, self.layout, self.layer_rows, self.slot_layers)
            old_objects, self._own["palette"] = self._own["palette"], []
            self.planes = ()
        self._drop_palette()
        self.layout, self.agents = layout, agents
        runs, self.runs = self.runs, 0
        self.layer_rows, self.slot_layers = layer_rows, slot_layers
        if agents == 0:
            return  # no agents: no palette, no layer texture, no pass
        layer_rows_needed = math.ceil(agents / self.layer_agents_per_row)
        # (the fragment path's layer texture and its pixel-unpack buffer, the same size; the compute path's buffer)
        need = 3 * width * layer_rows * layers * 16 + (2 if self.path == "fragment" else 1) * self.layer_agents_per_row * self.layer_count * layer_rows_needed * 16
        scratch = 4 if any(part.bake.residual is not None for part in self.parts) else 3
        if self.path == "fragment":
            need += scratch * width * layer_rows * slot_layers * 16  # (the locals pass's scratch)
        self.ctx.error  # clear an earlier error, so the check below sees these allocations'
        failure = None
        try:
            self.planes = tuple(self._array("palette", (width, layer_rows, layers)) for _ in range(3))
            self._make_layers(agents)
            # A layered framebuffer over the planes: it clears every layer at once (texels no run wrote
            # read as 0, not as whatever the memory held), and the fragment path renders through it.
            fb = self.ctx.framebuffer(color_attachments=list(self.planes))
            self._own["palette"].append(fb)
            if self.path == "fragment":  # the locals pass's scratch: one ring slot's shape (processor.frag.glsl)
                self._locals = tuple(self._array("locals", (width, layer_rows, slot_layers)) for _ in range(scratch))
                self._locals_framebuffer = self.ctx.framebuffer(color_attachments=list(self._locals))
                self._own["locals"].append(self._locals_framebuffer)
        except moderngl.Error as exc:
            failure = f"the palette for {agents:,} agents ({need:,} bytes) could not be made: {exc}"
        if failure is None and self.ctx.error == "GL_OUT_OF_MEMORY":
            failure = f"the GPU ran out of memory for the palette of {agents:,} agents: {need:,} bytes were needed"
        if failure is not None:
            self._drop_palette()
            self.layout, self.agents = self._layout([0] * len(self.parts)), 0
            for obj in old_objects:
                obj.release()
            raise ProcessorError(failure)
        fb.clear(0.0, 0.0, 0.0, 0.0)
        if self.path == "fragment":
            self._framebuffer = fb
        self._update_quads()
        if old is not None:
            try:
                self._copy_palettes(*old)
                self.runs = runs
            finally:
                for obj in old_objects:
                    obj.release()

    def _copy_palettes(self, planes, layout: PaletteLayout, layer_rows: int, slot_layers: int) -> None:
        """Copy each character's kept rows of every ring slot of the old `planes` (laid out by `layout`, in
        layers of `layer_rows` rows, `slot_layers` a slot) into the same character's rows of the same
        slots of the new planes, on the GPU: each old plane into a pixel-pack buffer, then runs of rows
        that stay in one layer on both sides through a staging buffer into the new plane. An agent's
        texel within its character's block depends only on its place in that block, and a resize keeps
        each character's first agents, so a block's first rows move as they are."""
        width = planes[0].size[0]
        row_bytes = width * 16
        new_width = self.planes[0].size[0]
        blocks = []  # (old first row, new first row, rows) per character, in slot-relative rows
        for a, b in zip(layout.parts, self.layout.parts):
            rows = min(a.rows, b.rows)
            if rows:
                blocks.append((a.first_row, b.first_row, rows))
        if not blocks:
            return
        staging = self.ctx.buffer(reserve=max(min(max(r for *_, r in blocks), layer_rows, self.layer_rows) * row_bytes, 16))
        whole = self.ctx.buffer(reserve=planes[0].size[0] * planes[0].size[1] * planes[0].layers * 16)
        try:
            for old_plane, new_plane in zip(planes, self.planes):
                old_plane.read_into(whole)
                for slot in range(self.history):
                    for old_first, new_first, rows in blocks:
                        y = 0
                        while y < rows:
                            oy, ny = old_first + y, new_first + y
                            old_layer, old_row = slot * slot_layers + oy // layer_rows, oy % layer_rows
                            new_layer, new_row = slot * self.slot_layers + ny // self.layer_rows, ny % self.layer_rows
                            count = min(rows - y, layer_rows - old_row, self.layer_rows - new_row)
                            self.ctx.copy_buffer(staging, whole, size=count * row_bytes, read_offset=(old_layer * layer_rows + old_row) * row_bytes)
                            new_plane.write(staging, viewport=(0, new_row, new_layer, min(width, new_width), count, 1))
                            y += count
        finally:
            staging.release()
            whole.release()

    def _make_layers(self, agents: int) -> None:
        """The layers' storage for `agents` agents (weight 0, the rest pose, until an upload), in place of
        the one before. The compute path reads a buffer, made at its first upload from the CPU (a crowd
        on the GPU hands its own, ``upload_from``). The fragment path reads a texture, whose whole rows
        go through a pixel-unpack buffer: a buffer write ran at about 14 GB/s on the H200 host where a
        texture write from the array ran at 2.6 (docs/BENCHMARKS.md, "The CPU side of the frame")."""
        self._release_group("layers")
        self.layers_texture = self._layer_unpack = self._layer_buffer = self._layers_source = None
        rows = self._layer_rows = math.ceil(agents / self.layer_agents_per_row)
        if self.path == "compute":
            return
        zeros = np.zeros((rows, self.layer_agents_per_row * self.layer_count, 4), np.float32)
        self.layers_texture = self._texture("layers", (self.layer_agents_per_row * self.layer_count, rows), 4, zeros, "f4")
        self._layer_unpack = self.ctx.buffer(reserve=zeros.nbytes)
        self._own["layers"].append(self._layer_unpack)

    def _drop_palette(self) -> None:
        """Release the palette planes, their framebuffer and the layer texture (the bakes' textures stay)."""
        self._release_group("palette")
        self._release_group("layers")
        self._release_group("locals")
        self.planes, self.layers_texture, self._framebuffer = (), None, None
        self._layer_unpack = self._layer_buffer = self._layers_source = None
        self._layer_rows = 0
        self._locals, self._locals_framebuffer = (), None

    def _array(self, group, size):
        tex = self.ctx.texture_array(size, 4, dtype="f4")
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._own[group].append(tex)
        return tex

    def _update_quads(self):
        """Fragment path: per character, the quads over its block's full palette rows and its partial last
        row, each cut at the layers of a ring slot, in one buffer (x, y in the layer's NDC, z the layer)."""
        if self.path != "fragment":
            return
        width, height = self.layout.width, self.layer_rows
        for part, block in zip(self.parts, self.layout.parts):
            full, partial = divmod(block.count, block.agents_per_row)
            spans = [(block.first_row, block.first_row + full, block.agents_per_row * block.width)]  # slot rows [y0, y1), width
            if partial:
                spans.append((block.first_row + full, block.first_row + full + 1, partial * block.width))
            verts = []
            for y0, y1, x1 in spans:
                y = y0
                while y < y1:
                    layer, row = divmod(y, height)
                    rows = min(y1 - y, height - row)
                    a, b = -1.0, 2.0 * x1 / width - 1.0
                    c, d = 2.0 * row / height - 1.0, 2.0 * (row + rows) / height - 1.0
                    verts += [(a, c, layer), (b, c, layer), (b, d, layer), (a, c, layer), (b, d, layer), (a, d, layer)]
                    y += rows
            part.quad_vertices = len(verts)
            data = np.asarray(verts, dtype=np.float32).tobytes()
            if part.quad is None or part.quad.size < max(len(data), 1):
                if part.quad is not None:
                    for obj in (part.quad_vao, part.locals_vao, part.quad):
                        self._own["processor_quad"].remove(obj)
                        obj.release()
                part.quad = self.ctx.buffer(reserve=max(len(data), 18 * 4))
                part.quad_vao = self.ctx.vertex_array(part.program, [(part.quad, "3f", "in_position")])
                part.locals_vao = self.ctx.vertex_array(part.locals_program, [(part.quad, "3f", "in_position")])
                self._own["processor_quad"] += [part.quad_vao, part.locals_vao, part.quad]
            if verts:
                part.quad.write(data)

    # -- the pass

    def run(self) -> bool:
        """Write every agent's palette row: one dispatch per character with agents (the fragment path: two
        draws, its locals pass and its compose pass, processor.frag.glsl). Returns
        False when nothing ran."""
        if self.agents == 0:
            return False
        slot = self.runs % self.history  # the ring slot this run writes
        if self.path == "compute":
            (self._layers_source if self._layers_source is not None else self._own_layers()).bind_to_storage_buffer(LAYERS_IN)
            for unit, plane in enumerate(self.planes):
                plane.bind_to_image(unit, read=False, write=True)
            for part, block in zip(self.parts, self.layout.parts):
                if block.count:
                    self._draw_part(part, block, slot, part.program)
        else:
            self.layers_texture.use(3)
            self.ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND | moderngl.CULL_FACE)
            # First every joint's blended local into the scratch, then the chains composed into the slot.
            self._locals_framebuffer.viewport = (0, 0, self.layout.width, self.layer_rows)
            self._locals_framebuffer.use()
            for part, block in zip(self.parts, self.layout.parts):
                if block.count:
                    self._draw_part(part, block, slot, part.locals_program)
            self._framebuffer.viewport = (0, 0, self.layout.width, self.layer_rows)
            self._framebuffer.use()
            for unit, plane in zip(LOCALS_UNITS, self._locals):
                plane.use(unit)
            for part, block in zip(self.parts, self.layout.parts):
                if block.count:
                    self._draw_part(part, block, slot, part.program)
        if self.path == "compute":
            # Later passes read the palette through texelFetch (and the readback through pack buffers).
            # The foot lock's next run reads the state this one wrote.
            self.ctx.memory_barrier(moderngl.TEXTURE_FETCH_BARRIER_BIT | moderngl.PIXEL_BUFFER_BARRIER_BIT | moderngl.TEXTURE_UPDATE_BARRIER_BIT
                                    | moderngl.SHADER_STORAGE_BARRIER_BIT)
        self.runs += 1
        return True

    def _draw_part(self, part: ProcessorPart, block, slot: int, prog) -> None:
        """One character's dispatch (compute) or draw (fragment: `prog` is its locals pass or its compose
        pass) over its block of the ring slot `slot`."""
        for unit, name in enumerate(("u_anim", "u_parents", "u_clips")):
            part.textures[name].use(unit)
        for unit, name in ((4, "u_anim_scale"), (5, "u_masks"), (6, "u_keys"), (7, "u_tracks"), (8, "u_morph_tracks"), (9, "u_morph_clips"),
                           (10, "u_morph_variation"), (11, "u_morph_held"), (15, "u_anim_residual")):
            # (the fragment path's compose pass has the scratch's fourth plane on the residual's unit)
            if name in part.textures and (name != "u_anim_residual" or self.path == "compute" or prog is part.locals_program):
                part.textures[name].use(unit)
        # One call: the units, the part's constants and the dispatch's rows, each written where it changed
        # since the program's last write (two characters of one source share a program).
        values = {**TEXTURE_UNITS, **part.uniforms, "u_row_offset": slot * self.slot_rows() + block.first_row,
                  # (The locals pass writes the scratch, one slot deep: its layers count from 0.)
                  "u_first_layer": 0 if prog is part.locals_program else slot * self.slot_layers, "u_palette_rows": self.layer_rows,
                  "u_agents": block.count, "u_first_agent": block.first_agent, "u_first_row": block.first_row,
                  "u_agents_per_row": block.agents_per_row}
        if part.held is not None:
            if part.held_written is not part.held:  # (hold_morphs makes a new array: written once a change)
                part.textures["u_morph_held"].write(part.held.tobytes())
                part.held_written = part.held
            values["u_morph_held_agent"] = part.held_agent
        if part.legs is not None:
            values.update(part.leg_bytes)  # (characters of one skeleton share them: written once)
            part.lock_state.bind_to_storage_buffer(0)
            part.lock_motion.bind_to_storage_buffer(1)
            values.update(u_lock_decay=math.exp(-self._lock_dt / lock.RELEASE_S), u_step_advance=self._lock_dt / lock.STEP_S)
        if block.key and self.path == "compute":
            if self._far is None:
                values["u_far_m"] = 0.0
            else:
                places, looks, eye, beyond, rows, masks = self._far
                places.bind_to_storage_buffer(FAR_PLACES)
                looks.bind_to_storage_buffer(FAR_LOOKS)
                values.update(u_far_eye=eye, u_far_m=beyond, u_far_rows=rows, u_far_joints=masks[self.parts.index(part)])
        set_uniforms(prog, **values)
        if self.path == "compute":
            groups = math.ceil(block.count / (GROUP_SIZE // block.width))
            gx = min(groups, 32768)
            prog.run(gx, math.ceil(groups / gx), 1)
        else:
            (part.locals_vao if prog is part.locals_program else part.quad_vao).render(moderngl.TRIANGLES, vertices=part.quad_vertices)

    def key_alone_beyond(self, places: moderngl.Buffer | None, looks: moderngl.Buffer | None = None, eye=(0.0, 0.0, 0.0),
                         beyond_m: float = 0.0, rows: int = 0, kept=()) -> None:
        """From the next run, the agents among the first `rows` (those of a crowd on the GPU, `places` its
        buffer of (x, z, vx, vz) from its origin, `looks` its (tint, head, weapon + 1, spawned step)) standing
        farther than `beyond_m` metres from `eye` (from the same origin) get their impostor key alone
        (crowd.draw.far_agents says when that is safe), and, those holding a weapon, the joints
        `kept[character]` (indices, with their ancestors; none where absent) besides. None: every row whole.
        Characters without impostors and the fragment path always write whole rows."""
        if places is None or self.path != "compute":
            self._far = None
            return
        key = tuple(None if joints is None else tuple(int(j) for j in joints) for joints in kept)
        if self._far_masks[0] != key:  # (the same every frame but for a new cast: made once)
            masks = []
            for k, part in enumerate(self.parts):
                bits = np.zeros(MAX_JOINTS, bool)
                parents = part.bake.parents
                for joint in (key[k] if k < len(key) and key[k] is not None else ()):
                    j = joint
                    while j >= 0 and not bits[j]:
                        bits[j] = True
                        j = int(parents[j])
                masks.append(joint_mask(np.flatnonzero(bits)))
            self._far_masks = (key, masks)
        self._far = (places, looks, tuple(float(v) for v in eye), float(beyond_m), int(rows), self._far_masks[1])

    def process(self, layers, motion=None, dt: float = 0.0) -> bool:
        self.upload(layers, motion, dt)
        return self.run()

    def reset_lock(self) -> None:
        """Every leg free with nothing carried (a new crowd in the same slots)."""
        for part in self.parts:
            if part.lock_state is not None:
                part.lock_state.clear()

    def hold_morphs(self, character: int, weights, agent: int) -> None:
        """Hold morph weights of one character from the next run: `weights` (M,), a weight in [0, 1] per
        target held, -1 where the clips and variation decide; `agent` its agent's number among the
        character's, or crowd.anim.morph.ALL_HELD / NOT_HELD. A character without morph tracks: ProcessorError."""
        part = self.parts[character]
        if part.held is None:
            raise ProcessorError(f"character {character} moves no morph target in this scene")
        w = np.asarray(weights, np.float32)
        if w.shape != part.held.shape or not np.all(np.isfinite(w)) or np.any(w > 1.0):
            raise ProcessorError(f"held morph weights must be {len(part.held)} values of at most 1 (-1: not held), got {np.asarray(weights).tolist()}")
        held = np.where(w >= 0.0, w, -1.0).astype(np.float32)
        if int(agent) != part.held_agent or not np.array_equal(held, part.held):  # (the texture is written when they change)
            part.held, part.held_agent = held, int(agent)

    def set_clip_loop(self, clip: int, loop: bool, character: int = 0) -> None:
        """Loop a clip of a character's bake (its phase wraps) or play it once (its phase clamps): that
        clip table is rewritten."""
        part = self.parts[character]
        if not 0 <= clip < len(part.bake.clips):
            raise ProcessorError(f"no clip {clip}; the bake has {len(part.bake.clips)}")
        part.bake.clips[clip] = dataclasses.replace(part.bake.clips[clip], loop=bool(loop))
        part.textures["u_clips"].write(np.ascontiguousarray(part.bake.clip_table).tobytes())

    def bind_palette(self, first_unit: int, *programs) -> None:
        """Bind the three planes (every palette of the history; texel codes say which rows) and tell
        `programs` (those that read them through shaders/palette.glsl) how many rows a layer holds."""
        for i, plane in enumerate(self.planes):
            plane.use(first_unit + i)
        for prog in programs:
            set_uniforms(prog, u_palette_rows=self.layer_rows)

    def gpu_bytes(self) -> dict[str, int]:
        return {group: gpu_bytes(objs) for group, objs in self._own.items()}

    def release(self) -> None:
        for group in list(self._own):
            self._release_group(group)
        self.planes, self.layers_texture, self._framebuffer = (), None, None
        self._layer_unpack, self._locals, self._locals_framebuffer = None, (), None
        self._layer_buffer = self._layers_source = None
        for part in self.parts:
            part.lock_state = part.lock_motion = part.quad = part.quad_vao = part.locals_vao = None
        for program in self._programs.values():
            program.release()
        self._programs = {}
