"""The GPU-driven frame's cull, LOD and compaction, for GL 4.3 contexts.

Contract, used by ``CrowdRenderer`` when its cull path is "gpu":
- the renderer writes every agent's record into the crowd's record buffer (crowd.draw.records), which this
  cull reads as a storage buffer;
- ``resize(cast)``: entry storage for that many agents per character;
- ``run(...)``: three dispatches of shaders/cull.comp.glsl that cull each agent's sphere against the view and
  each shadow cascade's box, pick its LOD (one coarser for shadows), and put its entry in every list it is in
  (crowd.draw.cull_lists: one per character, LOD and variation choice, read by every piece worn there),
  compacted by a prefix sum, and write each (pass, draw)'s DrawElementsIndirectCommand; the passes draw
  with ``render_indirect``;
- ``counts()``: the draws' instance counts as the CPU can know them without waiting: copied into a ring of 3
  small buffers behind fences and read once the GPU is done, so they trail the frame by a frame or two.

Storage: every pass's lists share one buffer of 4-byte entries, sized by the entries an agent can have (its
common pieces and one piece per variation group it has, twice in the view pass for a LOD fade, once per
cascade), not by draws x agents, so a character's piece count costs no memory per agent.

Morph twins: with ``run(..., palette=processor)``, an agent whose weights move no target goes to the STILL
part of its lists, which the plain twins of the morph draws read (cull_lists.py), so it costs what it would
in a scene without morphs.
"""

from __future__ import annotations

import math
from collections import deque
from typing import NamedTuple

import moderngl
import numpy as np

from ..errors import CrowdError
from ..gl import Fence, GLObjects, GLStage, load_shader, set_uniforms
from .cull_lists import RECORD_DTYPE, ListPlan
from .occlusion import HIZ_UNIT

GROUP_SIZE = 256
COMMAND_DTYPE = np.dtype([("count", "<u4"), ("instances", "<u4"), ("first_index", "<u4"), ("base_vertex", "<i4"), ("base_instance", "<u4")])
# cull.comp.glsl's Character, std430: a vec4 and nine 4-byte fields, padded to 64 bytes.
CHARACTER_DTYPE = np.dtype({"names": ["bound", "impostor_start", "lod_count", "steps", "starts", "table", "columns", "group_columns", "stats", "routed"],
                            "formats": [("<f4", (4,)), "<f4", "<i4", "<i4", "<i4", "<i4", "<i4", "<i4", "<i4", "<i4"],
                            "offsets": [0, 16, 20, 24, 28, 32, 36, 40, 44, 48], "itemsize": 64})
COUNT_RING = 3
SHARED_BYTES = 16384  # shared memory the work groups' counters may take (GL 4.3 promises 32 KB)
NEVER = 3.0e38  # float32's largest: "no limit"
ROUTE_UNIT = 0  # the cull reads the palette's first plane here


# glMemoryBarrier bits: what reads the shaders' writes (lists as vertex attributes, commands as
# draws, storage reads, and buffer copies and reads such as the counts ring's).
VERTEX_ATTRIB_ARRAY, COMMAND, BUFFER_UPDATE, SHADER_STORAGE = 0x1, 0x40, 0x200, 0x2000


class GpuCullError(CrowdError, ValueError):
    """A crowd the GPU cull cannot take; the message is one line."""


class CullCharacter(NamedTuple):
    """What the cull knows of one character of the cast beyond its lists: its bind pose's sphere (x, y, z,
    radius), the distances where its LOD 1, 2, ... start, the distance from which its agents are drawn as
    impostors (inf: never) and whether its agents are routed between morph draws and their plain twins."""

    bound: tuple
    lod_starts: tuple
    impostor_start: float = math.inf
    routed: bool = False


class CountRing:
    """Instance counts of indirect commands, handed back to the CPU without waiting: each frame's
    commands are copied into one of 3 small buffers behind a fence and read once the fence has
    signalled, so they trail the frame by a frame or two. Used by the body and the weapon culls."""

    def __init__(self, ctx: moderngl.Context, objects: GLObjects, commands: int, extra: int = 0):
        """`extra`: uint32 words after the commands that come back too (``latest_extra``)."""
        self.ctx = ctx
        self._commands = commands
        self._ring = [objects.add(ctx.buffer(reserve=commands * COMMAND_DTYPE.itemsize + extra * 4)) for _ in range(COUNT_RING)]
        self.latest_extra = np.zeros(extra, np.uint32)
        self._pending: deque = deque()  # (ring slot, fence) not yet read, oldest first
        self._next = 0
        self.latest = np.zeros(commands, np.uint32)

    def queue(self, commands: moderngl.Buffer) -> None:
        if len(self._pending) == COUNT_RING:  # the oldest copy is unread: drop it rather than wait
            self._pending.popleft()[1].release()
        slot = self._next
        self._next = (self._next + 1) % COUNT_RING
        self.ctx.copy_buffer(self._ring[slot], commands)
        self._pending.append((slot, Fence()))

    def zero(self) -> None:
        """Nothing to draw from now on (no agents): the counts are 0 at once."""
        self.drop()
        self.latest = np.zeros_like(self.latest)
        self.latest_extra = np.zeros_like(self.latest_extra)

    def read(self, wait: bool = False) -> np.ndarray:
        """The newest counts the GPU has finished (every queued frame's with `wait`)."""
        while self._pending:
            slot, fence = self._pending[0]
            if not wait and not fence.signaled():
                break
            if wait:
                fence.wait()
            self._pending.popleft()
            fence.release()
            data = self._ring[slot].read()
            size = self._commands * COMMAND_DTYPE.itemsize
            self.latest = np.frombuffer(data[:size], COMMAND_DTYPE)["instances"].copy()
            self.latest_extra = np.frombuffer(data[size:], np.uint32).copy()
        return self.latest

    def drop(self) -> None:
        for _, fence in self._pending:
            fence.release()
        self._pending = deque()


class GpuCull(GLStage):
    """Owns the lists' entries, the counters, the indirect commands of every pass, the tables that say
    which list an agent of a character at a LOD and choice is in, the per-agent visibility (only when
    `with_visible`: the weapons need it) and the ring the counts come back through."""

    def __init__(self, ctx: moderngl.Context, plan: ListPlan, draws: list[tuple[int, int, int]], characters: list[CullCharacter],
                 records: moderngl.Buffer, with_visible: bool, shadow_cascades: int = 0):
        """`plan`: the cast's lists and each draw's. `draws`: per draw (index count, first index, base vertex
        in the buffers it is drawn from). `characters`: the cast's, in its order. `records`: the crowd's record
        buffer (crowd.draw.records), which the cull reads (and the weapons' cull after it)."""
        self._objects = GLObjects()
        self.ctx = ctx
        self.agents_buffer = records
        self.plan = plan
        self.characters = list(characters)
        self.passes = 1 + int(shadow_cascades)
        self.cascades = int(shadow_cascades)
        self.draw_count = len(draws)
        self.lists = len(plan.keys)
        self.stats = int(plan.stats_first()[-1])
        counters = self.passes * self.lists * 2
        tallies = counters + self.stats
        self.per_agent = np.array([plan.per_agent(c) for c in range(len(characters))], np.int64)
        emits = int(self.per_agent.max()) * (2 + self.cascades)  # twice in the view across a fade, once per cascade
        self.shared = (tallies + counters + 256) * 4 <= SHARED_BYTES
        self.max_block = int(ctx.info.get("GL_MAX_SHADER_STORAGE_BLOCK_SIZE", 1 << 27))
        self.max_groups = int(ctx.info.get("GL_MAX_COMPUTE_WORK_GROUP_COUNT", (65535,))[0])
        defines = {"PASSES": self.passes, "GROUPS": plan.groups, "EMITS": max(emits, 1), "COUNTERS": counters, "TALLIES": tallies,
                   "SHARED_TALLIES": int(self.shared)}
        self.program = self._objects.add(ctx.compute_shader(load_shader("cull.comp.glsl", defines)))
        # Each sampler on a unit of its own from the start: the pyramid's sampler2D left on unit 0 beside
        # the palette's sampler2DArray there is an error GL need not report (the fetch then reads zeros).
        self.program["u_hiz"] = HIZ_UNIT
        self.program["u_palette0"] = ROUTE_UNIT
        self.routed_characters = any(c.routed for c in characters)
        tables, self._draw_table, self._choice_table, self._character_rows = self._tables()
        self.tables = self._objects.add(ctx.buffer(tables.tobytes()))
        self.character_buffer = self._objects.add(ctx.buffer(reserve=max(len(characters), 1) * CHARACTER_DTYPE.itemsize))
        self.lod_fade = 0.0  # metres past each LOD switch over which an agent is listed at both LODs (lod_fade.glsl)
        self.set_characters(self.characters)
        self.counters = self._objects.add(ctx.buffer(reserve=(tallies + counters) * 4))
        self.counters.clear()
        # The commands of every pass (pass p's draw d at p * draws + d): their index counts and offsets fixed,
        # their instance counts and first instances written by the scan; then the stats.
        commands = np.zeros(self.passes * self.draw_count, COMMAND_DTYPE)
        commands["count"] = np.tile([d[0] for d in draws], self.passes)
        commands["first_index"] = np.tile([d[1] for d in draws], self.passes)
        commands["base_vertex"] = np.tile([d[2] for d in draws], self.passes)
        self._template = commands.tobytes() + bytes(self.stats * 4)
        self.commands = self._objects.add(ctx.buffer(self._template))
        self.ring = CountRing(ctx, self._objects, self.passes * self.draw_count, self.stats)
        # Made once and re-sized in place (orphan keeps the GL name), so the vertex arrays built on the
        # entries stay valid when the crowd grows or shrinks.
        self.entries = self._objects.add(ctx.buffer(reserve=4))
        self.capacity = 0
        self.cast: tuple[int, ...] | None = None
        self.agents = 0
        self.visible = None
        self.set_visibility(with_visible)

    def _tables(self) -> tuple[np.ndarray, int, int, list[tuple]]:
        """The ints the shader looks things up in: each draw's (list, part), each group's (shift, bits) in a
        record's choices, then per character its LOD starts (float bits), its list table and its groups' first
        columns. Returns (tables, where the draws' pairs start, where the groups' start, per character
        (starts, table, columns, group columns))."""
        plan = self.plan
        out = [np.column_stack([plan.draw_list, plan.draw_part]).ravel()]
        at = 2 * self.draw_count
        choice_table = at
        out.append(np.column_stack([plan.choice_shift, plan.choice_bits]).ravel() if plan.groups else np.zeros(0, np.int64))
        at += 2 * plan.groups
        rows = []
        for c, character in enumerate(self.characters):
            starts = np.asarray(character.lod_starts, np.float32).view(np.int32).astype(np.int64)
            table = plan.table(c)
            rows.append((at, at + len(starts), table.shape[1], at + len(starts) + table.size))
            out += [starts, table.ravel(), plan.group_columns(c)]
            at += len(starts) + table.size + plan.groups
        return np.concatenate(out).astype(np.int32), 0, choice_table, rows

    def set_characters(self, characters: list[CullCharacter]) -> None:
        """The characters' bounds, LOD starts (same counts as built with), impostor distances and routing."""
        if len(characters) != len(self.characters) or any(len(a.lod_starts) != len(b.lod_starts) for a, b in zip(characters, self.characters)):
            raise GpuCullError("the cull's characters keep their count and their LOD switch counts")
        if any(tuple(a.lod_starts) != tuple(b.lod_starts) for a, b in zip(characters, self.characters)):
            self.characters = list(characters)
            tables, *_ = self._tables()
            self.tables.write(tables.tobytes())
        self.characters = list(characters)
        stats = self.plan.stats_first()
        info = np.zeros(len(characters), CHARACTER_DTYPE)
        for c, (character, (starts, table, columns, group_columns)) in enumerate(zip(characters, self._character_rows)):
            info[c]["bound"] = character.bound
            info[c]["impostor_start"] = min(character.impostor_start, NEVER)
            info[c]["lod_count"] = self.plan.mesh_lods[c]
            info[c]["steps"] = len(character.lod_starts)
            info[c]["starts"], info[c]["table"], info[c]["columns"], info[c]["group_columns"] = starts, table, columns, group_columns
            info[c]["stats"] = stats[c]
            info[c]["routed"] = int(character.routed)
        self.character_buffer.write(info.tobytes())

    def set_visibility(self, on: bool) -> None:
        """Keep (or drop) the per-agent visibility the weapons' cull reads: it exists only with weapons."""
        if on and self.visible is None:
            self.visible = self._objects.add(self.ctx.buffer(reserve=max(self.agents, 1) * 4))
        elif not on and self.visible is not None:
            self._objects.remove(self.visible)
            self.visible.release()
            self.visible = None

    # -- storage

    def resize(self, cast) -> None:
        """Entries for `cast` agents per character (4 bytes for 0, which frees the rest); the same counts
        keep them. A crowd whose entries pass what this GPU lets one shader address, or its memory, is
        refused in one line saying how many bytes it needed."""
        cast = tuple(int(c) for c in cast)
        if cast == self.cast:
            return
        if len(cast) != len(self.characters):
            raise GpuCullError(f"agent counts for {len(cast)} characters, the cull draws {len(self.characters)}")
        agents = sum(cast)
        capacity = int(np.dot(np.asarray(cast, np.int64), self.per_agent)) * (2 + self.cascades)
        need = capacity * 4
        if need > self.max_block or agents * RECORD_DTYPE.itemsize > self.max_block:
            raise GpuCullError(f"the GPU cull's lists for {agents:,} agents need {max(need, agents * RECORD_DTYPE.itemsize):,} bytes, "
                               f"more than the {self.max_block:,} one shader storage block may hold on this GPU (GL_MAX_SHADER_STORAGE_BLOCK_SIZE): "
                               "fewer agents, or --cull feedback or cpu")
        if (agents + GROUP_SIZE - 1) // GROUP_SIZE > self.max_groups:
            raise GpuCullError(f"{agents:,} agents need more than the {self.max_groups:,} work groups one dispatch may have: fewer agents, or --cull feedback or cpu")
        self.ctx.error  # clear any earlier error, so the check below sees this allocation's
        self.cast, self.capacity = cast, capacity
        self.entries.orphan(max(need, 4))
        if self.visible is not None:
            self.visible.orphan(max(agents, 1) * 4)
        if self.ctx.error == "GL_OUT_OF_MEMORY":
            self.cast = None  # the next resize tries again
            raise GpuCullError(f"the GPU ran out of memory for the GPU cull's {need:,} bytes of lists for {agents:,} agents")

    def entry_bytes(self) -> int:
        """Bytes the lists of every pass hold together."""
        return self.entries.size

    # -- per frame

    def upload(self, agents: int, cast) -> None:
        """This frame's crowd: `agents` records in the record buffer, `cast` the agents of each character."""
        self.resize(cast)
        self.agents = int(agents)
        if not self.agents:  # (the passes draw from the commands without knowing: the last crowd's must not stay)
            self.commands.write(self._template)
            self.ring.zero()

    def run(self, planes: np.ndarray, culling: bool = True, shadow_planes=None, reach=None, occlusion=None,
            palette=None, held=(-1, 0.0, 0.0)) -> None:
        """Cull the agents into every pass's lists and commands: the view (`planes` (6, 4)) and
        each cascade (`shadow_planes` (cascades, 6, 4), `reach` (cascades,) metres from the eye past which an
        agent casts nothing there). `occlusion`: (the previous frame's DepthPyramid, this frame's eye) to test
        the view's agents against too. `palette`: the processor whose newest palette the draws read
        (bind_palette), so agents moving no morph target go to the plain twins (None: every agent of a morph
        piece to its morph draw). `held`: (the group of the weapons impostors hold or -1, the view's pixels a
        metre spans at a metre's depth, and the pixels an impostor's bound must span in the view to hold one)."""
        n = self.agents
        if n == 0:
            return
        p = self.program
        if occlusion is not None and culling:
            occlusion[0].bind(p, occlusion[1])
        else:
            set_uniforms(p, u_occlusion=0)
        volumes = np.zeros((self.passes, 6, 4), np.float32)
        reaches = np.full(self.passes, NEVER, np.float32)
        volumes[0] = planes
        if self.cascades:
            if shadow_planes is None:
                raise GpuCullError("this cull keeps shadow lists: give each cascade's planes")
            volumes[1:] = np.asarray(shadow_planes, np.float32)[: self.cascades]
            if reach is not None:
                reaches[1:] = np.minimum(np.asarray(reach, np.float64)[: self.cascades], NEVER)
        routing = palette is not None and self.routed_characters
        if routing:
            palette.bind_palette(ROUTE_UNIT, p)
        # (Written where they changed since the last frame; set_uniforms leaves out what the compiler dropped.)
        set_uniforms(p, u_planes=volumes.tobytes(), u_reach=reaches.tobytes(), u_culling=int(bool(culling)), u_lod_fade=float(self.lod_fade),
                     u_routing=int(routing), u_agents=n, u_lists=self.lists, u_draws=self.draw_count, u_draw_table=self._draw_table,
                     u_choice_table=self._choice_table, u_stats=self.stats, u_write_visible=int(self.visible is not None),
                     u_held_group=int(held[0]), u_focal_px=float(held[1]), u_held_px=float(held[2]) if held[1] > 0.0 else 0.0)
        for binding, buffer in enumerate((self.agents_buffer, self.entries, self.counters, self.commands, self.tables, self.character_buffer, self.visible)):
            if buffer is not None:
                buffer.bind_to_storage_buffer(binding)
        groups = (n + GROUP_SIZE - 1) // GROUP_SIZE
        for phase, size in ((0, groups), (1, 1), (2, groups)):
            set_uniforms(p, u_phase=phase)
            p.run(group_x=size)
            self.ctx.memory_barrier(SHADER_STORAGE)
        # The entries feed vertex attributes and the commands feed the draws: both written by the shader.
        self.ctx.memory_barrier(VERTEX_ATTRIB_ARRAY | COMMAND | BUFFER_UPDATE)
        self.ring.queue(self.commands)

    def counts(self, wait: bool = False) -> np.ndarray:
        """(draws,) instance counts of the view's draws, of the newest frame the GPU has finished (every
        queued one with `wait`); never waits otherwise."""
        return self.ring.read(wait)[: self.draw_count]

    def shadow_counts(self, wait: bool = False) -> np.ndarray:
        """As ``counts``, for the shadow cascades' draws: (cascades, draws)."""
        return self.ring.read(wait)[self.draw_count:].reshape(self.cascades, self.draw_count)

    def agent_counts(self) -> np.ndarray:
        """(characters, most LOD slots) agents the view kept, per character and the LOD each was drawn at
        (its coarser across a fade), of the frame ``counts`` last read."""
        first = self.plan.stats_first()
        out = np.zeros((len(self.characters), max(self.plan.lod_slots)), np.int64)
        for c in range(len(self.characters)):
            out[c, : first[c + 1] - first[c]] = self.ring.latest_extra[first[c]:first[c + 1]]
        return out

    def listed(self, draw: int, cascade: int | None = None) -> np.ndarray:
        """uint32 entries the last run gave draw `draw` in the view (or `cascade`'s) pass (synchronous: tests)."""
        k = draw + (0 if cascade is None else 1 + cascade) * self.draw_count
        command = np.frombuffer(self.commands.read(COMMAND_DTYPE.itemsize, offset=k * COMMAND_DTYPE.itemsize), COMMAND_DTYPE)[0]
        if not command["instances"]:
            return np.zeros(0, np.uint32)
        return np.frombuffer(self.entries.read(int(command["instances"]) * 4, offset=int(command["base_instance"]) * 4), np.uint32).copy()

    def visible_agents(self) -> np.ndarray:
        """(N,) LOD + 1 of each agent, 0 where culled, plus bit 16 + k where it is in shadow cascade k's
        volume and then its shadow LOD << 20 (synchronous: tests)."""
        if self.visible is None:
            raise GpuCullError("this cull keeps no per-agent visibility (no weapons)")
        return np.frombuffer(self.visible.read(), np.uint32)[: self.agents].copy()

    def gpu_bytes(self) -> int:
        return self._objects.gpu_bytes()

    def release(self) -> None:
        if hasattr(self, "_objects"):
            if hasattr(self, "ring"):
                self.ring.drop()
            self._objects.release()
