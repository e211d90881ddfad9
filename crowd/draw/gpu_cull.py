"""The GPU-driven frame's cull, LOD and compaction (issue 19, points 1 and 2), for GL 4.3 contexts.

Contract, used by ``CrowdRenderer`` when its cull path is "gpu":
- ``upload(records)``: one buffer of every agent's 32-byte record (camera-relative position and scale,
  palette texel, tint, heading, variation choices), written in one upload, with no per-agent Python
  and no sort;
- ``run(planes, ...)``: one compute dispatch (shaders/cull.comp.glsl) that culls each agent's sphere,
  picks its LOD and appends its record to the list of each (piece, LOD) draw it is in, counting it in
  that draw's DrawElementsIndirectCommand; the passes then draw with ``render_indirect``;
- ``counts()``: the draws' instance counts as the CPU can know them without waiting: copied into a
  ring of 3 small buffers behind fences and read once the GPU is done, so they trail the frame by a
  frame or two (the stats and the panel use them; ``counts(wait=True)`` is for tests).

Shadows: with shadows on, one more dispatch per shadow cascade (crowd.draw.shadows) culls the same
records against that cascade's orthographic box into lists and commands of its own, one LOD coarser
than the colour pass would pick (``run_shadow``); with shadows off they do not exist.

Lists: draw d's list is records [start_d, start_d + capacity_d) of one buffer, its capacity being the
agent count of its character (the cast's characters each have their draws: crowd.frame), so one atomic
add per (agent, piece) places a record with no second pass; the commands' baseInstance points each
draw at its list. The price is memory: each character's draws x its agents x 32 bytes (12 draws of the
zombie at 1,000,000 agents: 384 MB), which ``gpu_bytes`` reports.

Morph twins: a draw of a piece with morph targets may have a plain twin, the same geometry drawn by the
program without morph code. With ``run(..., palette=processor)``, an agent whose weights move no target
(the first pair the processor wrote before its joint 0 has weight 0) is listed in the twins instead,
so it costs what it would in a scene without morphs. A twin has no list of its own: it fills its morph
draw's list from the end (its baseInstance counts down), so twins cost no memory per agent.

Several characters: each agent's record carries its character (bits 28-31 of its variation field), and
the cull looks up that character's bound, LOD count, pieces and variation groups.
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple

import moderngl
import numpy as np

from ..gl import Fence, GLObjects, GLStage, load_shader
from .occlusion import HIZ_UNIT

GROUP_SIZE = 256
RECORD_DTYPE = np.dtype([("position_scale", "<f4", 4), ("packed", "<u4", 4)])
COMMAND_DTYPE = np.dtype([("count", "<u4"), ("instances", "<u4"), ("first_index", "<u4"), ("base_vertex", "<i4"), ("base_instance", "<u4")])
MAX_GROUPS = 7  # variation groups: 4 bits each in packed.w, below the character's 4 bits
MAX_CAST = 16  # characters: crowd.frame.MAX_CAST
CHARACTER_SHIFT = 28  # where packed.w keeps the agent's character
MAX_CHOICES = 16
MAX_LOD_STEPS = 4
MAX_DRAWS = 256  # (piece, LOD) draws: the cull's shared counters (cull.comp.glsl)
MAX_EMITS = 16  # draws one agent is in: its common pieces and one piece per variation group
COUNT_RING = 3
LOD_SLOTS = 8  # per character, the colour cull's agents counted per LOD (mesh LODs and the impostor), after the commands
FILLS_DOWN = -2  # cull_common.glsl's route entry of a plain twin
ROUTE_UNIT = 0  # the cull reads the palette's first plane here


# glMemoryBarrier bits: what reads the shaders' writes (lists as vertex attributes, commands as
# draws, storage reads, and buffer copies and reads such as the counts ring's).
VERTEX_ATTRIB_ARRAY, COMMAND, BUFFER_UPDATE, SHADER_STORAGE = 0x1, 0x40, 0x200, 0x2000


class GpuCullError(ValueError):
    """A crowd the GPU cull cannot take; the message is one line."""


class CullCharacter(NamedTuple):
    """What the cull knows of one character of the cast: the slots of the pieces all its agents wear
    (common_first .. common_first + common - 1), the first slot of each variation group's choices (-1
    where it has no such group), its mesh LOD count, its bind pose's sphere (x, y, z, radius), and the
    distance from which its agents are drawn as impostors (LOD lod_count: crowd.draw.impostors; inf: never)."""

    common_first: int
    common: int
    group_slots: tuple
    lod_count: int
    bound: tuple
    impostor_start: float = float("inf")


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
    """Owns the agent records, the per-draw lists, the indirect commands, the per-agent visibility
    (only when `with_visible`: the weapons need it) and the ring the counts come back through."""

    def __init__(self, ctx: moderngl.Context, draws: list[tuple], characters: list[CullCharacter], group_choices: list[int],
                 with_visible: bool, shadow_cascades: int = 0):
        """`draws`: per draw (LOD, slot, index count, first index, base vertex in the buffers it is drawn
        from, character[, the index of the morph draw it is the plain twin of, -1 for none]). `characters`: the cast's, in its order (CullCharacter: which slots are whose).
        `group_choices`: the largest choice count of each variation group, over the cast."""
        self._objects = GLObjects()
        self.ctx = ctx
        if len(characters) > MAX_CAST:
            raise GpuCullError(f"the GPU cull takes up to {MAX_CAST} characters, this cast has {len(characters)}")
        if len(group_choices) > MAX_GROUPS or any(c > MAX_CHOICES for c in group_choices):
            raise GpuCullError(f"the GPU cull takes up to {MAX_GROUPS} variation groups of up to {MAX_CHOICES} pieces, "
                               f"this cast has {len(group_choices)} groups of {', '.join(map(str, group_choices))}")
        worn = max(c.common + sum(1 for g in c.group_slots if g >= 0) for c in characters)
        if any(c.lod_count + 1 > LOD_SLOTS for c in characters):
            raise GpuCullError(f"the GPU cull counts up to {LOD_SLOTS - 1} mesh LODs a character")
        if 2 * worn > MAX_EMITS:  # an agent in a LOD fade is listed at two LODs
            raise GpuCullError(f"an agent wears {worn} pieces, more than the {MAX_EMITS // 2} the GPU cull lists (twice, across a LOD fade)")
        if len(draws) > MAX_DRAWS:
            raise GpuCullError(f"{len(draws)} (piece, LOD) draws, more than the {MAX_DRAWS} the GPU cull counts")
        self.draw_count = len(draws)
        self.index_counts = np.array([d[2] for d in draws], np.uint32)
        self.first_index = np.array([d[3] for d in draws], np.uint32)
        self.base_vertex = np.array([d[4] for d in draws], np.int32)
        self.draw_character = np.array([d[5] for d in draws], np.int64)
        self.characters = list(characters)
        self.groups = len(group_choices)
        self.slots = max(max(d[1] for d in draws) + 1, 1)
        lods = max(d[0] for d in draws) + 1
        twin_of = np.array([d[6] if len(d) > 6 else -1 for d in draws], np.int64)
        self.twin_of = twin_of
        table = np.full(lods * self.slots, -1, np.int32)
        route = np.full(self.draw_count, -1, np.int32)  # cull_common.glsl's route: twin, FILLS_DOWN or -1
        for k, (lod, slot, *_) in enumerate(draws):
            if twin_of[k] >= 0:
                if draws[twin_of[k]][:6] != tuple(draws[k][:6]) or twin_of[twin_of[k]] >= 0:
                    raise GpuCullError(f"draw {k} is not a copy of the draw {twin_of[k]} it is said to be the plain twin of")
                route[twin_of[k]], route[k] = k, FILLS_DOWN
            else:
                table[lod * self.slots + slot] = k
        # Characters whose agents are routed: those with a twin (the cull reads their morph pairs).
        self.routed_characters = sum(1 << int(self.draw_character[d]) for d in np.flatnonzero(twin_of >= 0))
        self.program = self._objects.add(ctx.compute_shader(load_shader("cull.comp.glsl")))
        # Each sampler on a unit of its own from the start: the pyramid's sampler2D left on unit 0 beside
        # the palette's sampler2DArray there is an error GL need not report (the fetch then reads zeros).
        self.program["u_hiz"] = HIZ_UNIT
        self.program["u_palette0"] = ROUTE_UNIT
        self.draw_of = self._objects.add(ctx.buffer(table.tobytes()))
        self.route = self._objects.add(ctx.buffer(route.tobytes()))
        self.list_start = self._objects.add(ctx.buffer(reserve=self.draw_count * 4))
        # The commands, then per (character, LOD) the colour cull's agents (each once, at the LOD it is
        # drawn at: an agent in a fade is in two LODs' lists but counts at the coarser).
        self.commands = self._objects.add(ctx.buffer(reserve=self.draw_count * COMMAND_DTYPE.itemsize + len(characters) * LOD_SLOTS * 4))
        self.ring = CountRing(ctx, self._objects, self.draw_count, len(characters) * LOD_SLOTS)
        self.max_block = int(ctx.info.get("GL_MAX_SHADER_STORAGE_BLOCK_SIZE", 1 << 27))
        self.max_groups = int(ctx.info.get("GL_MAX_COMPUTE_WORK_GROUP_COUNT", (65535,))[0])
        # Made once and re-sized in place (orphan keeps the GL name), so the vertex arrays built on
        # the lists stay valid when the crowd grows or shrinks.
        self.agents = 0
        self.cast: tuple[int, ...] | None = None  # agents per character the lists are sized for
        self.starts = np.zeros(self.draw_count, np.int64)  # each draw's first record in the lists
        self.records = 0  # the colour lists' records: every draw's capacity
        self.agents_buffer = self._objects.add(ctx.buffer(reserve=RECORD_DTYPE.itemsize))
        self.lists = self._objects.add(ctx.buffer(reserve=RECORD_DTYPE.itemsize))
        self.lod_fade = 0.0  # metres past each LOD switch over which an agent is listed at both LODs (lod_fade.glsl)
        self.cascades = shadow_cascades  # cascade k's lists and commands follow cascade k - 1's
        self.shadow_lists = self.shadow_commands = self.shadow_ring = None
        if shadow_cascades:
            self.shadow_lists = self._objects.add(ctx.buffer(reserve=RECORD_DTYPE.itemsize))
            self.shadow_commands = self._objects.add(ctx.buffer(reserve=shadow_cascades * self.draw_count * COMMAND_DTYPE.itemsize))
            self.shadow_ring = CountRing(ctx, self._objects, shadow_cascades * self.draw_count)
        self.visible = None
        self.set_visibility(with_visible)

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
        """Storage for a crowd of `cast` agents per character (or one count for a one-character cast; a
        record's worth for 0, which frees the rest); the same counts keep it. A crowd whose lists pass
        what this GPU lets one shader address, or its memory, is refused in one line saying how many
        bytes it needed."""
        cast = (int(cast),) if isinstance(cast, (int, np.integer)) else tuple(int(c) for c in cast)
        if cast == self.cast:
            return
        if len(cast) != len(self.characters):
            raise GpuCullError(f"agent counts for {len(cast)} characters, the cull draws {len(self.characters)}")
        agents = sum(cast)
        capacity = np.asarray(cast, np.int64)[self.draw_character]  # each draw's list holds its character's agents
        capacity[self.twin_of >= 0] = 0  # a twin writes into its morph draw's list
        records = int(capacity.sum())
        need = records * RECORD_DTYPE.itemsize * max(self.cascades, 1)  # the largest list buffer
        if need > self.max_block:
            raise GpuCullError(f"the GPU cull's lists for {agents:,} agents need {need:,} bytes, more than the {self.max_block:,} "
                               "one shader storage block may hold on this GPU")
        if (agents + GROUP_SIZE - 1) // GROUP_SIZE > self.max_groups:
            raise GpuCullError(f"{agents:,} agents need more than the {self.max_groups:,} work groups one dispatch may have")
        self.ctx.error  # clear any earlier error, so the check below sees this allocation's
        self.cast, self.records = cast, records
        self.starts = np.concatenate([[0], np.cumsum(capacity)[:-1]]).astype(np.int64)
        twins = np.flatnonzero(self.twin_of >= 0)
        self.starts[twins] = self.starts[self.twin_of[twins]]
        self.list_start.write(self.starts.astype(np.uint32).tobytes())
        self.agents_buffer.orphan(max(agents, 1) * RECORD_DTYPE.itemsize)
        self.lists.orphan(max(records, 1) * RECORD_DTYPE.itemsize)
        if self.shadow_lists is not None:
            self.shadow_lists.orphan(max(self.cascades * records, 1) * RECORD_DTYPE.itemsize)
        if self.visible is not None:
            self.visible.orphan(max(agents, 1) * 4)
        if self.ctx.error == "GL_OUT_OF_MEMORY":
            self.cast = None  # the next resize tries again
            lists = records * RECORD_DTYPE.itemsize * (1 + self.cascades)
            raise GpuCullError(f"the GPU ran out of memory for the GPU cull's {lists + agents * RECORD_DTYPE.itemsize:,} bytes of lists "
                               f"and records for {agents:,} agents")

    def list_of(self, d: int, cascade: int | None = None) -> tuple[int, int]:
        """(first record, capacity) of draw d's colour list, or of its list in a shadow cascade (a plain
        twin's: its morph draw's, which it shares)."""
        capacity = self.cast[self.draw_character[d]] if self.cast is not None else 0
        return int(self.starts[d]) + (0 if cascade is None else cascade * self.records), int(capacity)

    def drawn_records(self, d: int, count: int, cascade: int | None = None) -> slice:
        """Where the `count` records draw d drew lie in its list buffer: from the list's start, or for a
        plain twin at its end."""
        first, capacity = self.list_of(d, cascade)
        if self.twin_of[d] >= 0:
            return slice(first + capacity - count, first + capacity)
        return slice(first, first + count)

    # -- per frame

    def upload(self, records: np.ndarray, cast=None) -> None:
        """This frame's agent records (RECORD_DTYPE), in one write, `cast` the agents of each character
        (None: all of the one character); the commands start from zero."""
        n = len(records)
        self.resize((n,) if cast is None else cast)
        self.agents = n
        commands = np.zeros(self.draw_count, COMMAND_DTYPE)
        commands["count"] = self.index_counts
        commands["first_index"] = self.first_index
        commands["base_vertex"] = self.base_vertex
        commands["base_instance"] = self.starts
        twins = self.twin_of >= 0
        if self.cast is not None and twins.any():  # a twin counts down from its shared list's end
            ends = self.starts[twins] + np.asarray(self.cast, np.int64)[self.draw_character[twins]]
            commands["base_instance"][twins] = ends.astype(np.uint32)
        self.commands.write(commands.tobytes() + bytes(len(self.characters) * LOD_SLOTS * 4))
        if self.shadow_commands is not None:
            shadow = np.tile(commands, self.cascades)
            shadow["base_instance"] = np.tile(commands["base_instance"].astype(np.int64), self.cascades) + np.repeat(np.arange(self.cascades, dtype=np.int64) * self.records, self.draw_count)
            self.shadow_commands.write(shadow.tobytes())
        if n:
            self.agents_buffer.write(records)  # the array itself (contiguous): no copy of 32 bytes an agent
        else:
            self.ring.zero()
            if self.shadow_ring is not None:
                self.shadow_ring.zero()

    def run(self, planes: np.ndarray, margin: float, lod_start, culling: bool, occlusion=None, palette=None) -> None:
        """Cull the uploaded agents into the colour pass's lists and commands (one dispatch), each against
        its character's bound, at most its character's LODs; `occlusion`: (the previous frame's
        DepthPyramid, this frame's eye) to test them against too. `palette`: the processor whose newest
        palette the draws read (bind_palette), so agents moving no morph target go to the plain twins
        (None: every agent of a morph piece to its morph draw)."""
        self._route(palette)
        self._dispatch(self.lists, self.commands, self.ring, planes, margin, lod_start, culling, 0, self.visible, 1, occlusion=occlusion)

    def _route(self, palette) -> None:
        mask = self.routed_characters if palette is not None else 0
        self.program["u_routing"] = mask
        if mask:
            palette.bind_palette(ROUTE_UNIT, self.program)

    def run_shadow(self, planes: np.ndarray, lod_start, culling: bool, reach=None, palette=None) -> None:
        """Cull the uploaded agents against each cascade's box (`planes` (cascades, 6, 4)) into that
        cascade's shadow lists, one LOD coarser; each agent in cascade k's box gets bit 16 + k of its
        visibility (after ``run``, which clears it): the weapons' shadow pass keeps their weapons.
        `reach` (cascades,): metres from the eye past which an agent casts nothing into that cascade.
        `palette`: as for ``run``."""
        self._route(palette)
        for k, cascade_planes in enumerate(planes):
            self._dispatch(self.shadow_lists, self.shadow_commands, None, cascade_planes, 0.0, lod_start, culling, 1,
                           self.visible, 2, cascade=k, reach=np.inf if reach is None else float(reach[k]))
        if self.agents:
            self.shadow_ring.queue(self.shadow_commands)

    def _dispatch(self, lists, commands, ring, planes, margin, lod_start, culling, lod_bias, visible, mode,
                  cascade: int = 0, occlusion=None, reach: float = np.inf) -> None:
        n = self.agents
        if n == 0:
            return
        p = self.program
        if occlusion is not None and culling:
            occlusion[0].bind(p, occlusion[1])
        else:
            p["u_occlusion"] = 0
        p["u_planes"].write(np.ascontiguousarray(planes, np.float32).tobytes())
        bounds = np.zeros((MAX_CAST, 4), np.float32)
        bounds[: len(self.characters)] = [c.bound for c in self.characters]
        p["u_bound"].write(bounds.tobytes())
        p["u_margin"] = float(margin)
        p["u_reach"] = float(min(reach, 3.0e38))  # float32's largest: "no limit"
        starts = np.zeros(MAX_LOD_STEPS, np.float32)
        starts[: len(lod_start)] = lod_start
        p["u_lod_start"].write(starts.tobytes())
        p["u_lod_steps"] = len(lod_start)
        per_character = np.zeros((3, MAX_CAST), np.int32)  # LOD count, first common slot, common count
        per_character[:, : len(self.characters)] = np.array([(c.lod_count, c.common_first, c.common) for c in self.characters]).T
        for row, name in enumerate(("u_lod_count", "u_common_first", "u_common")):
            p[name].write(per_character[row].tobytes())
        impostor_start = np.full(MAX_CAST, 3.0e38, np.float32)  # float32's largest: "never"
        impostor_start[: len(self.characters)] = [min(c.impostor_start, 3.0e38) for c in self.characters]
        p["u_impostor_start"].write(impostor_start.tobytes())
        p["u_culling"] = int(bool(culling))
        p["u_lod_fade"] = float(self.lod_fade)
        p["u_count_agents"] = int(mode == 1)
        p["u_count_base"] = self.draw_count * 5
        p["u_agents"] = n
        p["u_slots"] = self.slots
        p["u_groups"] = self.groups
        if self.groups:
            slots = np.full((MAX_CAST, MAX_GROUPS), -1, np.int32)
            for k, c in enumerate(self.characters):
                slots[k, : len(c.group_slots)] = c.group_slots
            p["u_group_slot"].write(slots.tobytes())
        p["u_write_visible"] = mode if visible is not None else 0
        p["u_lod_bias"] = int(lod_bias)
        p["u_draws"] = self.draw_count
        p["u_cascade"] = cascade
        p["u_list_base"] = cascade * self.draw_count
        p["u_record_base"] = cascade * self.records
        self.agents_buffer.bind_to_storage_buffer(0)
        lists.bind_to_storage_buffer(1)
        commands.bind_to_storage_buffer(2)
        self.draw_of.bind_to_storage_buffer(3)
        self.list_start.bind_to_storage_buffer(6)
        self.route.bind_to_storage_buffer(7)
        if visible is not None:
            visible.bind_to_storage_buffer(4)
        p.run(group_x=(n + GROUP_SIZE - 1) // GROUP_SIZE)
        # The lists feed vertex attributes and the commands feed the draws: both written by the shader.
        self.ctx.memory_barrier(VERTEX_ATTRIB_ARRAY | COMMAND | BUFFER_UPDATE | SHADER_STORAGE)
        if ring is not None:
            ring.queue(commands)

    def counts(self, wait: bool = False) -> np.ndarray:
        """(draws,) instance counts of the newest frame the GPU has finished (every queued one with
        `wait`); never waits otherwise."""
        return self.ring.read(wait)

    def agent_counts(self) -> np.ndarray:
        """(characters, LOD_SLOTS) agents the colour cull kept, per character and the LOD each was drawn at
        (its coarser across a fade), of the frame ``counts`` last read."""
        return self.ring.latest_extra.reshape(len(self.characters), LOD_SLOTS)

    def shadow_counts(self, wait: bool = False) -> np.ndarray:
        """As ``counts``, for the shadow lists: (cascades, draws) (none without shadows)."""
        if self.shadow_ring is None:
            return np.zeros((0, self.draw_count), np.uint32)
        return self.shadow_ring.read(wait).reshape(self.cascades, self.draw_count)

    def visible_agents(self) -> np.ndarray:
        """(N,) LOD + 1 of each agent, 0 where culled, plus bit 16 + k where it is in shadow cascade k's
        volume and then its shadow LOD << 20 (synchronous: tests)."""
        if self.visible is None:
            raise GpuCullError("this cull keeps no per-agent visibility (no weapons)")
        return np.frombuffer(self.visible.read(), np.uint32).copy()

    def gpu_bytes(self) -> int:
        return self._objects.gpu_bytes()

    def release(self) -> None:
        if hasattr(self, "_objects"):
            if hasattr(self, "ring"):
                self.ring.drop()
            if getattr(self, "shadow_ring", None) is not None:
                self.shadow_ring.drop()
            self._objects.release()
