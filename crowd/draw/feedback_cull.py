"""The cull, LOD and per-draw lists of GL 4.0 to 4.2 contexts (issue 25, point 2): macOS's 4.1 core, and
any context the "gl" setting caps at 4.1. They have no compute shaders, storage buffers, multi-draw-indirect
or baseInstance, but they have transform feedback with a geometry shader, four vertex streams, feedback
objects that keep what each stream wrote (glDrawTransformFeedbackStream) and glDrawElementsIndirect (all
GL 4.0): enough to keep the CPU out of the per-agent work, as the compute cull (crowd.draw.gpu_cull) does.

Contract, used by ``CrowdRenderer`` when its cull path is "feedback":
- the renderer writes every agent's 32-byte record into the crowd's record buffer (crowd.draw.records), which
  the feedback draws read as vertex attributes; ``upload(agents, cast)`` sizes the lists for that crowd;
- ``run(planes, ...)``: the lists, in feedback draws of one character's agents as points through
  shaders/feedback_cull.*.glsl, each filling 4 lists: the vertex shader makes the compute cull's
  decision (feedback_pick.glsl: the sphere against the view's or a cascade's planes, the LOD, the fade
  band, the variation choice) for each, the geometry shader emits the agent on the stream of each list
  it is in, and transform feedback appends its 4-byte entry (crowd.draw.cull_lists) to that list's buffer. Then each list is counted on the
  GPU (``FeedbackCounter``) into one DrawElementsIndirectCommand per (pass, draw), packed into the command
  buffer by glReadPixels: nothing waits;
- ``draw(vao, draw, cascade)``: glDrawElementsIndirect of that command;
- ``counts()``: the commands as the CPU can know them without waiting (a frame or two late, through the
  compute cull's CountRing); ``agent_counts()``: the agents per LOD, from a plain point pass;
- with weapons, ``visible``: an R32UI texture of each agent's visibility word (the compute cull's
  ``visible`` buffer: colour LOD + 1, or 0 where culled or held by its impostor; the shadow cascades it
  is in, with its shadow LOD), one point per agent into its texel, which the weapons' feedback cull reads.

Lists: those of crowd.draw.cull_lists, one per (character, LOD, group, choice) and pass, read by every piece
worn there. A list is a buffer of its own (GL 4.1's commands have no baseInstance), of 4 bytes for each agent
its character has (an agent is in a list at most once: across a fade it is in two LODs' lists).
Shadow lists are culled against the cascade's box one LOD coarser, as on the compute path, so a cascade
has no list at LOD 0 (unless the character has one LOD). Agents moving no morph target are not routed
to plain twins here (the CPU path does not route them either), and there is no occlusion culling.

Why this shape, measured on the H200 (crowd-bench feedback, docs/BENCHMARKS.md): a feedback draw costs
about 5 ns an agent whatever it writes, against 0.3 to 0.6 ns for a plain point draw, so the cost is the
feedback draws' agents: a draw per list took 22 ms for 100,000 agents; four lists a draw (one per stream)
take a quarter of that. Counting stays off the feedback draws: the number of records a stream wrote
reaches a buffer only through a query the CPU reads (a stall) or a query buffer (GL 4.4), so
glDrawTransformFeedbackStream draws one point per record into the list's block of a float texture with
additive blending (exact: integers below 2^24 a texel), spread over COUNT_BLOCK x COUNT_BLOCK texels as
points blended into one texel wait for one another, and two fragment passes sum the blocks into commands.
"""

from __future__ import annotations

import ctypes
import moderngl
import numpy as np

from ..errors import CrowdError
from ..gl import GLObjects, GLStage, current_context_function, load_shader
from .cull_lists import ListKey, ListPlan
from .gpu_cull import COMMAND_DTYPE, CountRing, CullCharacter
from .records import use_records_unit

STREAMS = 4  # lists one feedback draw fills: GL 4.0's vertex streams (GL_MAX_VERTEX_STREAMS is at least 4)
COUNT_BLOCK = 64  # the side of the block of texels each list's records are counted over (a power of two)
VISIBLE_WIDTH = 2048  # agents a row of the visibility texture
NEVER = 3.0e38  # float32's largest: "no limit"

_GL_TRANSFORM_FEEDBACK, _GL_TRANSFORM_FEEDBACK_BUFFER, _GL_POINTS, _GL_TRIANGLES = 0x8E22, 0x8C8E, 0x0, 0x4
_GL_DRAW_INDIRECT_BUFFER, _GL_UNSIGNED_INT = 0x8F3F, 0x1405


class FeedbackCullError(CrowdError, ValueError):
    """A crowd the transform-feedback cull cannot take; the message is one line."""


_api: dict | None = None


def _gl() -> dict:
    """The GL entry points moderngl does not offer (feedback objects and streams, glDrawElementsIndirect),
    loaded once; all GL 4.0 core. moderngl keeps no cache of the program, vertex array or buffer bindings
    these change: each of its draws binds its own."""
    global _api
    if _api is None:
        void, uint, int_, ptr = None, ctypes.c_uint, ctypes.c_int, ctypes.c_void_p
        uints = ctypes.POINTER(ctypes.c_uint)
        types = {"glUseProgram": (void, uint), "glBindVertexArray": (void, uint), "glBindBufferBase": (void, uint, uint, uint),
                 "glBeginTransformFeedback": (void, uint), "glEndTransformFeedback": (void,), "glDrawArrays": (void, uint, int_, int_),
                 "glBindBuffer": (void, uint, uint), "glDrawElementsIndirect": (void, uint, uint, ptr),
                 "glGenTransformFeedbacks": (void, int_, uints), "glDeleteTransformFeedbacks": (void, int_, uints),
                 "glBindTransformFeedback": (void, uint, uint), "glDrawTransformFeedbackStream": (void, uint, uint, uint)}
        _api = {name: current_context_function(name, ctypes.CFUNCTYPE(*sig)) for name, sig in types.items()}
    return _api


class TransformFeedbacks:
    """GL transform-feedback objects (moderngl has none): each keeps its buffers' bindings and what each of
    its streams wrote. Released with the stage's other objects; they hold no memory of their own."""

    def __init__(self, count: int):
        self.names = (ctypes.c_uint * max(count, 1))()
        self.count = count
        if count:
            _gl()["glGenTransformFeedbacks"](count, self.names)

    def __getitem__(self, k: int) -> int:
        return int(self.names[k])

    def release(self) -> None:
        if self.count:
            _gl()["glDeleteTransformFeedbacks"](self.count, self.names)
            self.count = 0


def stream_varyings(names: list[str]) -> list[str]:
    """The varyings of a 4-stream geometry shader whose stream s writes block `S<s>`'s members `names`, each
    stream into a buffer of its own (gl_NextBuffer, GL 4.0)."""
    out = []
    for s in range(STREAMS):
        out += [f"S{s}.{name}" for name in names] + (["gl_NextBuffer"] if s + 1 < STREAMS else [])
    return out


def capture(program: moderngl.Program, vao: moderngl.VertexArray, feedback: int, into: list[moderngl.Buffer], first: int, count: int) -> None:
    """One feedback draw: `count` points of `vao` from `first` through `program`, whose stream s is appended
    to `into[s]` (feedback object `feedback` keeps what each wrote). The rasterizer must be off."""
    gl = _gl()
    # (glUseProgram is not allowed while feedback is active: bind first, then begin)
    gl["glUseProgram"](program.glo)
    gl["glBindVertexArray"](vao.glo)
    gl["glBindTransformFeedback"](_GL_TRANSFORM_FEEDBACK, feedback)
    for s, buffer in enumerate(into):
        gl["glBindBufferBase"](_GL_TRANSFORM_FEEDBACK_BUFFER, s, buffer.glo)
    gl["glBeginTransformFeedback"](_GL_POINTS)
    gl["glDrawArrays"](_GL_POINTS, int(first), int(count))
    gl["glEndTransformFeedback"]()
    gl["glBindTransformFeedback"](_GL_TRANSFORM_FEEDBACK, 0)


class FeedbackCounter:
    """The counting half of a transform-feedback cull, shared by the bodies' and the weapons': a float
    texture of blocks of COUNT_BLOCK x COUNT_BLOCK texels (one a list, and any more a caller counts into
    itself), the passes that turn them into DrawElementsIndirectCommands, the command buffer that is packed
    into, and the ring the counts come back to the CPU through. Its GL objects join `objects`."""

    def __init__(self, ctx: moderngl.Context, objects: GLObjects, commands: list[tuple[int, int]], blocks: int,
                 stats: tuple[int, int] = (0, 0)):
        """`commands`: per command, (its index count, the block its instance count is read from); `blocks`:
        how many; `stats`: (first block, count) of blocks whose sums come back too (``stats()``)."""
        self.ctx = ctx
        self.rows, self.blocks = len(commands), blocks
        limit = int(ctx.info.get("GL_MAX_TEXTURE_SIZE", 16384))
        self.block = COUNT_BLOCK
        while self.block > 1 and blocks * self.block > limit:  # (many lists: smaller blocks, so they fit)
            self.block //= 2
        self.stats_first, self.stats = stats
        stat_rows = (self.stats + 4) // 5
        if blocks > limit or self.rows + stat_rows > limit:
            raise FeedbackCullError(f"{blocks} lists and {self.rows} draws need count textures larger than this GPU's {limit} texels")
        self.texture = objects.add(ctx.texture((blocks * self.block, self.block), 1, dtype="f4"))
        self.target = objects.add(ctx.framebuffer([self.texture]))
        self.partials = objects.add(ctx.texture((blocks, self.block), 1, dtype="u4"))
        self.partials_target = objects.add(ctx.framebuffer([self.partials]))
        table = np.array(commands, np.uint32).reshape(-1, 2)
        self.table = objects.add(ctx.texture((max(self.rows, 1), 1), 2, table.tobytes() if self.rows else bytes(8), dtype="u4"))
        self.commands_texture = objects.add(ctx.texture((5, max(self.rows + stat_rows, 1)), 1, dtype="u4"))
        self.commands_target = objects.add(ctx.framebuffer([self.commands_texture]))
        fullscreen = load_shader("feedback_commands.vert.glsl")
        self._partial = objects.add(ctx.program(vertex_shader=fullscreen, fragment_shader=load_shader("feedback_partial.frag.glsl")))
        self._commands = objects.add(ctx.program(vertex_shader=fullscreen, fragment_shader=load_shader("feedback_commands.frag.glsl")))
        self._count = objects.add(ctx.program(vertex_shader=load_shader("feedback_count.vert.glsl"), fragment_shader=load_shader("feedback_count.frag.glsl")))
        for name, value in (("u_counts", 0), ("u_count_block", self.block)):
            self._partial[name] = value
        for name, value in (("u_partials", 0), ("u_draw_table", 1), ("u_count_block", self.block), ("u_rows", self.rows),
                            ("u_stats_first", self.stats_first), ("u_stats", self.stats)):
            self._commands[name] = value
        self._count["u_count_block"] = self.block
        self._count["u_count_size"] = tuple(float(x) for x in self.texture.size)
        self._partial_vao = objects.add(ctx.vertex_array(self._partial, []))
        self._commands_vao = objects.add(ctx.vertex_array(self._commands, []))
        self._count_vao = objects.add(ctx.vertex_array(self._count, []))
        self.commands = objects.add(ctx.buffer(reserve=max(self.rows + stat_rows, 1) * 5 * 4))
        self.ring = CountRing(ctx, objects, self.rows, stat_rows * 5)

    def begin(self) -> None:
        """Clear the counts and set the additive blend ``count_stream`` and a caller's own points use."""
        self.target.use()
        self.target.viewport = (0, 0, *self.texture.size)
        self.target.clear(0.0)
        self.ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.RASTERIZER_DISCARD)  # every point counts
        self.ctx.enable(moderngl.BLEND)
        self.ctx.blend_func = moderngl.ONE, moderngl.ONE

    def uniforms(self, program: moderngl.Program, block: int) -> None:
        """Point `program` (a caller's counting points, as feedback_census.vert.glsl) at `block`."""
        program["u_count_texel"] = (block * self.block, 0)
        program["u_count_block"] = self.block
        program["u_count_size"] = tuple(float(x) for x in self.texture.size)

    def count_stream(self, feedback: int, stream: int, block: int) -> None:
        """Add what stream `stream` of feedback object `feedback` wrote into `block` (after ``begin``)."""
        gl = _gl()
        self._count["u_count_texel"] = (block * self.block, 0)
        gl["glUseProgram"](self._count.glo)
        gl["glBindVertexArray"](self._count_vao.glo)
        gl["glDrawTransformFeedbackStream"](_GL_POINTS, feedback, stream)

    def finish(self) -> None:
        """The commands from the counts, packed into the command buffer on the GPU; queued for the CPU."""
        self.ctx.disable(moderngl.BLEND)
        self.ctx.blend_func = moderngl.DEFAULT_BLENDING
        self.texture.use(0)
        self.partials_target.use()
        self.partials_target.viewport = (0, 0, *self.partials.size)
        self._partial_vao.render(moderngl.TRIANGLES, vertices=3)
        self.partials.use(0)
        self.table.use(1)
        self.commands_target.use()
        self.commands_target.viewport = (0, 0, *self.commands_texture.size)
        self._commands_vao.render(moderngl.TRIANGLES, vertices=3)
        # Rows in order: row r's 5 words are command r, then the stats.
        self.commands_target.read_into(self.commands, components=1, dtype="u4")
        self.ring.queue(self.commands)

    def draw(self, vao: moderngl.VertexArray, row: int) -> None:
        """Draw `vao` (its program set, its instances command `row`'s list) as many times as counted,
        from the command on the GPU."""
        gl = _gl()
        gl["glUseProgram"](vao.program.glo)
        gl["glBindVertexArray"](vao.glo)
        gl["glBindBuffer"](_GL_DRAW_INDIRECT_BUFFER, self.commands.glo)
        gl["glDrawElementsIndirect"](_GL_TRIANGLES, _GL_UNSIGNED_INT, ctypes.c_void_p(row * COMMAND_DTYPE.itemsize))
        gl["glBindBuffer"](_GL_DRAW_INDIRECT_BUFFER, 0)

    def zero(self) -> None:
        """Nothing listed from now on: every command draws nothing, and the counts are 0 at once."""
        self.commands.clear()
        self.ring.zero()

    def counts(self, wait: bool = False) -> np.ndarray:
        """(rows,) instance counts of the newest frame the GPU has finished (every queued one with `wait`);
        never waits otherwise."""
        return self.ring.read(wait)

    def stat_counts(self) -> np.ndarray:
        """(stats,) the stats blocks' sums, of the frame ``counts`` last read."""
        return self.ring.latest_extra[: self.stats]


def stream_groups(slots: list, key) -> list[list[int]]:
    """Slot indices in groups of up to STREAMS that share `key(slot)` (a feedback draw covers one
    character's agents), in order."""
    groups: list[list[int]] = []
    open_group: dict = {}
    for index, slot in enumerate(slots):
        k = key(slot)
        group = open_group.get(k)
        if group is None or len(group) == STREAMS:
            group = open_group[k] = []
            groups.append(group)
        group.append(index)
    return groups


class FeedbackCull(GLStage):
    """Owns a buffer per list (of each pass), the feedback objects, the counter (counts, commands and the ring
    they come back through) and, with `with_visible`, each agent's visibility for the weapons."""

    def __init__(self, ctx: moderngl.Context, plan: ListPlan, index_counts: list[int], characters: list[CullCharacter],
                 records, shadow_cascades: int = 0, with_visible: bool = False):
        """`plan`: the cast's lists and each draw's; `index_counts`: each draw's; `characters`: the cast's, in
        its order; `records`: the crowd's AgentRecords (crowd.draw.records)."""
        self._objects = GLObjects()
        self.ctx = ctx
        if shadow_cascades > 2:
            raise FeedbackCullError(f"the feedback cull culls up to 2 shadow cascades, got {shadow_cascades}")
        self.plan = plan
        self.characters = list(characters)
        self.cascades = shadow_cascades
        self.keys: tuple[ListKey, ...] = plan.keys
        self.draw_count = len(index_counts)
        mesh_lods = plan.mesh_lods
        # The lists (key, pass) that can hold anything: a cascade's are one LOD coarser, so never at LOD 0
        # of a character with more than one.
        self.slots = [(key, 0) for key in self.keys]
        self.slots += [(key, 1 + k) for k in range(shadow_cascades) for key in self.keys if key.lod > 0 or mesh_lods[key.character] == 1]
        self.slots.sort(key=lambda slot: slot[0].character)  # (stable: a character's lists, then the next one's)
        slot_of = {slot: index for index, slot in enumerate(self.slots)}
        self.groups = stream_groups(self.slots, lambda slot: slot[0].character)
        # Blocks: one a list, one that is never counted into (a (pass, draw) with no list: 0), then per
        # character one per LOD slot for the stats' agents per LOD.
        empty = len(self.slots)
        self.census_first = empty + 1
        self.stats_first = plan.stats_first()
        stats = int(self.stats_first[-1])
        commands = [(count, slot_of.get((self.keys[int(plan.draw_list[d])], p), empty)) for p in range(1 + shadow_cascades)
                    for d, count in enumerate(index_counts)]
        self.counter = FeedbackCounter(ctx, self._objects, commands, self.census_first + stats, stats=(self.census_first, stats))
        steps = {"STEPS": max(max(len(c.lod_starts) for c in characters), 1)}
        self.program = self._objects.add(ctx.program(vertex_shader=load_shader("feedback_cull.vert.glsl", steps),
                                                     geometry_shader=load_shader("feedback_cull.geom.glsl"),
                                                     varyings=stream_varyings(["entry"])))
        self._census = self._objects.add(ctx.program(vertex_shader=load_shader("feedback_census.vert.glsl", steps),
                                                     fragment_shader=load_shader("feedback_count.frag.glsl")))
        self._steps = steps
        self._records = records
        self.records = records.buffer
        use_records_unit(self.program)
        self._indices = self._objects.add(ctx.buffer(reserve=4))  # 0 .. agents - 1 (feedback_cull.vert.glsl says why)
        self._agents_vao = self._objects.add(ctx.vertex_array(self.program, [(self._indices, "1u", "in_agent")]))
        self._census_vao = self._objects.add(ctx.vertex_array(self._census, [(records.buffer, "4f 16x", "in_position_scale")]))
        # Made once and re-sized in place (orphan keeps the GL name), so the draws' vertex arrays on the
        # lists stay valid when the crowd grows or shrinks.
        self.lists = [self._objects.add(ctx.buffer(reserve=4)) for _ in self.slots]
        self._spare = self._objects.add(ctx.buffer(reserve=4))  # a group's unused streams write nothing here
        self.feedbacks = self._objects.add(TransformFeedbacks(len(self.groups)))
        self._uniforms: dict[int, frozenset] = {}
        self._slot_of = slot_of
        self.cast: tuple[int, ...] | None = None
        self.first_agent = np.zeros(len(characters), np.int64)  # each character's first agent in the records
        self.agents = 0
        self.lod_fade = 0.0
        self.visible = self._visible_target = self._visible_program = self._visible_vao = None
        self.with_visible = False
        self.set_visibility(with_visible)

    def set_visibility(self, on: bool) -> None:
        """Keep (or drop) each agent's visibility, which the weapons' feedback cull reads: only with weapons."""
        self.with_visible = bool(on)
        if on and self._visible_program is None:
            self._visible_program = self._objects.add(self.ctx.program(vertex_shader=load_shader("feedback_visible.vert.glsl", self._steps),
                                                                       fragment_shader=load_shader("feedback_visible.frag.glsl")))
            self._visible_vao = self._objects.add(self.ctx.vertex_array(self._visible_program, [(self.records, "4f 16x", "in_position_scale")]))
        if not on:
            self._drop_visible_texture()
        elif self.cast is not None:
            self._size_visible(sum(self.cast))

    def set_characters(self, characters: list[CullCharacter]) -> None:
        """The characters' bounds, LOD starts, impostor distances (each frame's uniforms come from them)."""
        if len(characters) != len(self.characters) or max(len(c.lod_starts) for c in characters) > self._steps["STEPS"]:
            raise FeedbackCullError("the cull's characters keep their count, and no more LOD switches than it was built for")
        self.characters = list(characters)

    def _drop_visible_texture(self) -> None:
        for obj in (self._visible_target, self.visible):
            if obj is not None:
                self._objects.remove(obj)
                obj.release()
        self.visible = self._visible_target = None

    def _size_visible(self, agents: int) -> None:
        """A texel per agent, VISIBLE_WIDTH a row: made again only when the rows change."""
        size = (VISIBLE_WIDTH, max((agents + VISIBLE_WIDTH - 1) // VISIBLE_WIDTH, 1))
        if self.visible is not None and self.visible.size == size:
            return
        self._drop_visible_texture()
        self.visible = self._objects.add(self.ctx.texture(size, 1, dtype="u4"))
        self._visible_target = self._objects.add(self.ctx.framebuffer([self.visible]))

    def list_buffer(self, draw: int, cascade: int | None = None) -> moderngl.Buffer:
        """The buffer draw `draw` reads its entries from: its list in the colour pass, or in `cascade`'s
        (a spare, never written, where a cascade has no list at its LOD)."""
        slot = self._slot_of.get((self.keys[int(self.plan.draw_list[draw])], 0 if cascade is None else 1 + cascade))
        return self._spare if slot is None else self.lists[slot]

    # -- storage

    def resize(self, cast: tuple[int, ...]) -> None:
        """Lists for `cast` agents per character (the same counts keep them; 0 agents frees them)."""
        if cast == self.cast:
            return
        if len(cast) != len(self.characters):
            raise FeedbackCullError(f"agent counts for {len(cast)} characters, the cull draws {len(self.characters)}")
        self.ctx.error  # clear any earlier error, so the check below sees this allocation's
        self.cast = cast
        self.first_agent = np.concatenate([[0], np.cumsum(cast)[:-1]]).astype(np.int64)
        for (key, _), buffer in zip(self.slots, self.lists):
            buffer.orphan(max(cast[key.character], 1) * 4)
        self._indices.orphan(max(sum(cast), 1) * 4)
        if sum(cast):
            self._indices.write(np.arange(sum(cast), dtype=np.uint32))
        if self.with_visible:
            self._size_visible(sum(cast))
        if self.ctx.error == "GL_OUT_OF_MEMORY":
            self.cast = None  # the next resize tries again
            need = sum(cast[key.character] for key, _ in self.slots) * 4
            raise FeedbackCullError(f"the GPU ran out of memory for the feedback cull's {need:,} bytes of lists for {sum(cast):,} agents")

    def entry_bytes(self) -> int:
        """Bytes the lists of every pass hold together."""
        return sum(b.size for b in self.lists)

    # -- per frame

    def upload(self, agents: int, cast) -> None:
        """This frame's crowd: `agents` records in the record buffer, `cast` the agents of each character."""
        self.resize(tuple(int(c) for c in cast))
        self.agents = int(agents)
        if not self.agents:  # (the passes draw from the commands without knowing: the last crowd's must not stay)
            self.counter.zero()

    def _set_character(self, program: moderngl.Program, k: int, culling: bool) -> None:
        """feedback_pick.glsl's uniforms for character `k` (those a program uses: the census reads no fade)."""
        c = self.characters[k]
        starts = np.zeros(self._steps["STEPS"], np.float32)
        starts[: len(c.lod_starts)] = c.lod_starts
        program["u_lod_start"].write(starts.tobytes())
        values = {"u_lod_steps": len(c.lod_starts), "u_culling": int(bool(culling)), "u_bound": tuple(float(x) for x in c.bound),
                  "u_lod_count": self.plan.mesh_lods[k], "u_impostor_start": float(min(c.impostor_start, NEVER)), "u_lod_fade": float(self.lod_fade)}
        names = self._uniforms.setdefault(program.glo, frozenset(program))  # (a program's names, listed once: `in` walks them all)
        for name, value in values.items():
            if name in names:
                program[name] = value

    def _set_volumes(self, program: moderngl.Program, planes, shadow_planes, reach) -> None:
        program["u_planes"].write(np.ascontiguousarray(planes, np.float32).tobytes())
        cascades = 0 if shadow_planes is None else min(len(shadow_planes), self.cascades)
        program["u_cascades"] = cascades
        light = np.zeros((12, 4), np.float32)
        reaches = np.full(2, NEVER, np.float32)
        if cascades:
            light[: 6 * cascades] = np.asarray(shadow_planes, np.float32)[:cascades].reshape(-1, 4)
            reaches[:cascades] = [min(float(r), NEVER) for r in (reach if reach is not None else [np.inf] * cascades)][:cascades]
        program["u_shadow_planes"].write(light.tobytes())
        program["u_shadow_reach"].write(reaches.tobytes())

    def run(self, planes: np.ndarray, culling: bool, shadow_planes: np.ndarray | None = None, reach=None) -> None:
        """Fill every list of the colour pass (`planes`: the view's (6, 4)) and, with `shadow_planes`
        ((cascades, 6, 4)) and `reach` ((cascades,) metres from the eye past which an agent casts nothing
        there), each shadow cascade's; count them into the commands; with weapons, each agent's visibility.
        Nothing waits on the GPU."""
        if not self.agents:
            return
        p = self.program
        self._set_volumes(p, planes, shadow_planes, reach)
        self._records.bind()
        self.counter.target.use()  # (a draw needs a complete framebuffer bound, even one that writes no pixels)
        self.ctx.enable(moderngl.RASTERIZER_DISCARD)  # (the feedback draws write lists, not pixels)
        try:
            current = None
            for g, group in enumerate(self.groups):
                character = self.slots[group[0]][0].character
                if not self.cast[character]:
                    continue
                if character != current:  # (a character's groups follow one another: its uniforms once)
                    self._set_character(p, character, culling)
                    current = character
                passes, lods, shifts, bits, choices = [-1] * STREAMS, [0] * STREAMS, [-1] * STREAMS, [0] * STREAMS, [0] * STREAMS
                for s, index in enumerate(group):
                    key, passes[s] = self.slots[index]
                    lods[s], choices[s] = key.lod, key.choice
                    if key.group >= 0:
                        shifts[s], bits[s] = self.plan.choice_shift[key.group], self.plan.choice_bits[key.group]
                p["u_slot_pass"], p["u_slot_lod"], p["u_slot_shift"], p["u_slot_bits"], p["u_slot_choice"] = passes, lods, shifts, bits, choices
                into = [self.lists[index] for index in group] + [self._spare] * (STREAMS - len(group))
                capture(p, self._agents_vao, self.feedbacks[g], into, self.first_agent[character], self.cast[character])
        finally:
            self.ctx.disable(moderngl.RASTERIZER_DISCARD)
        self.counter.begin()
        for g, group in enumerate(self.groups):
            if self.cast[self.slots[group[0]][0].character]:
                for s, index in enumerate(group):
                    self.counter.count_stream(self.feedbacks[g], s, index)
        census = self._census
        census["u_planes"].write(np.ascontiguousarray(planes, np.float32).tobytes())
        for k, count in enumerate(self.cast):
            if count:
                self._set_character(census, k, culling)
                self.counter.uniforms(census, self.census_first + int(self.stats_first[k]))
                self._census_vao.render(moderngl.POINTS, vertices=count, first=int(self.first_agent[k]))
        self.counter.finish()
        if self.with_visible and self.visible is not None:
            self._write_visible(planes, culling, shadow_planes, reach)

    def _write_visible(self, planes, culling, shadow_planes, reach) -> None:
        v = self._visible_program
        self._set_volumes(v, planes, shadow_planes, reach)
        v["u_size"] = self.visible.size
        self._visible_target.use()
        self._visible_target.viewport = (0, 0, *self.visible.size)
        self._visible_target.clear()
        self.ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)
        for k, count in enumerate(self.cast):
            if count:
                self._set_character(v, k, culling)
                self._visible_vao.render(moderngl.POINTS, vertices=count, first=int(self.first_agent[k]))

    def visible_agents(self) -> np.ndarray:
        """(N,) each agent's visibility word (as the compute cull's ``visible_agents``; synchronous: tests)."""
        if self.visible is None:
            raise FeedbackCullError("this cull keeps no per-agent visibility (no weapons)")
        return np.frombuffer(self.visible.read(), np.uint32)[: self.agents].copy()

    def draw(self, vao: moderngl.VertexArray, draw: int, cascade: int | None = None) -> None:
        """Draw `vao` (its program set, its instances ``list_buffer(draw, cascade)``) as many times as the
        cull listed."""
        self.counter.draw(vao, draw + (0 if cascade is None else (1 + cascade) * self.draw_count))

    def counts(self, wait: bool = False) -> np.ndarray:
        """(draws,) instance counts of the colour pass, of the newest frame the GPU has finished (every
        queued one with `wait`); never waits otherwise."""
        return self.counter.counts(wait)[: self.draw_count]

    def shadow_counts(self, wait: bool = False) -> np.ndarray:
        """(cascades, draws) instance counts of the shadow lists, as ``counts``."""
        return self.counter.counts(wait)[self.draw_count:].reshape(self.cascades, self.draw_count)

    def agent_counts(self) -> np.ndarray:
        """(characters, most LOD slots) agents the colour pass kept, per character and the LOD each is drawn
        at (its coarser across a fade), of the frame ``counts`` last read."""
        stats = self.counter.stat_counts().astype(np.int64)
        out = np.zeros((len(self.characters), max(self.plan.lod_slots)), np.int64)
        for c in range(len(self.characters)):
            out[c, : self.stats_first[c + 1] - self.stats_first[c]] = stats[self.stats_first[c]:self.stats_first[c + 1]]
        return out

    def listed(self, draw: int, cascade: int | None = None) -> np.ndarray:
        """uint32 entries of draw `draw`'s list in the view (or `cascade`'s) pass, as many as counted
        (synchronous: tests)."""
        count = int(self.counter.counts(wait=True)[draw + (0 if cascade is None else (1 + cascade) * self.draw_count)])
        return np.frombuffer(self.list_buffer(draw, cascade).read(), np.uint32)[:count].copy()

    def gpu_bytes(self) -> int:
        return self._objects.gpu_bytes()

    def release(self) -> None:
        if hasattr(self, "_objects"):
            if hasattr(self, "counter"):
                self.counter.ring.drop()
            self._objects.release()
