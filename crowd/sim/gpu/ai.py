"""The crowd AI as compute passes (GL 4.3): the numpy CrowdAI's behaviour, stepped on the GPU with its
state in storage buffers (crowd.sim.gpu.state), nothing per agent through the CPU in a step.

A substep is four kinds of pass, each the twin of a numpy phase:
- think (shaders/sim/think.comp.glsl, THINK_A): timers and transitions, respawn and wander points from
  the keyed draws, steering and the substep's motion (crowd.sim.think ``_think_a``);
- the grid (crowd.sim.gpu.grid) of the living agents and the separation's push from it
  (shaders/sim/separation.comp.glsl; crowd.sim.separation);
- finish (think.comp.glsl, FINISH): the push, the bounds, heading, the turn about the planted foot and
  the phase (``_apply_range`` and ``_think_b``);
and, once a step, the layers (shaders/sim/outputs.comp.glsl; crowd.sim.outputs) into a buffer the
processor reads. The player's blows are passes too (shaders/sim/hit.comp.glsl).

Where it differs from the numpy AI, and why:
- float32 state, positions relative to the origin (crowd.sim.gpu.state says what that holds);
- every agent thinks every substep: the think budget was the CPU's way to afford a big crowd, and on the
  GPU a think costs less than the bookkeeping that would skip it;
- the grid is rebuilt every substep instead of kept as a Verlet list while nobody has moved half the
  radius: a build is a few passes over the agents, and the pairs within the radius are the same set.

Deterministic: the keyed draws depend on (seed, agent, substep, purpose) only, the grid's cells are
sorted by agent number, each push is summed in that order, and the counts are integer atomics."""

from __future__ import annotations

import contextlib
import math

import moderngl
import numpy as np

from ...gl import GLObjects, GLStage, has_compute, load_shader, set_uniforms
from ...frame import SimFrame, cast_firsts
from ..config import STATE_NAMES, AIError
from ..obstacles import FLOW_CELLS
from ..separation import SEPARATION_CELL_CAP, grid_shape, kind_radii
from ..spawn import _ARMS, _LOOKS, _MASK64, _PLACE, _RESPAWN, _TRAITS, _WANDER, PLACE_TRIES, TINTS, draw_bound
from .facts import facts_of
from .grid import GROUP, SHADER_STORAGE, NeighbourGrid

READ_BACK = SHADER_STORAGE | 0x200 | 0x80  # and buffer updates (copies, reads) and pixel-buffer reads (a texture's upload) of what a pass wrote
from .state import FIELDS, SCRATCH_BINDING, kind_table, pack, pivot_table, unpack

PIVOTS, LAYERS_OUT, COUNTERS = 9, 9, 8  # storage bindings beside the state's (the layers and the pivots are never bound together)
COUNTER_WORDS = 36  # blows, respawns, kills, hurt, 8 state counts, 2 nearest distances, 2 nearest agents, where a look's nearest
# stands, the count near a point, a selected agent with its motion, heading and codes, and a pick's answer (shaders/sim/agents.glsl)
PICK_WORD = 32
STRIKE, LOOK = 0, 1  # the two nearest searches' slots
GROUND, ENTRIES = 10, 10  # the foot motion's ground points; the overrides' list
FIELD, FLOW = 11, 12  # the town's distance field and flow field (the think and finish passes')
_FIELD_NAMES = tuple(FIELDS)


class GpuAIError(AIError):
    """The GPU AI cannot run here, or was handed bad input; one line."""


class GpuCrowdAI(GLStage):
    """The crowd's state on the GPU and its step. Built from a numpy CrowdAI (``load``), whose crowd it
    continues; ``store`` writes the GPU's crowd back into one. Scalars (time, substeps, the player, the
    world's size) stay on the CPU and go in as uniforms."""

    def __init__(self, ctx: moderngl.Context, ai, fresh: bool = False):
        if not has_compute(ctx):
            raise GpuAIError(f"the GPU AI needs GL 4.3 compute shaders; this context is GL {ctx.version_code // 100}.{ctx.version_code % 100 // 10}")
        self.ctx = ctx
        self._objects = GLObjects()
        self._state: dict[str, moderngl.Buffer] = {}
        self.grid = self._objects.add(NeighbourGrid(ctx, live_only=True))
        self.sent_bytes = 0  # bytes written from the CPU since the caller last zeroed it (counters, a blow's list)
        self.timer = None  # something with .gpu(name), a context manager timing the passes inside (crowd.timing.PassTimer)
        self.n = 0
        self.load(ai, fresh)

    # -- the crowd in and out

    def load(self, ai, fresh: bool = False) -> None:
        """Take over the crowd of a numpy CrowdAI: its agents' state, its clock and its settings. `fresh`:
        `ai` is a crowd just spawned (no step yet), whose agents the GPU spawns from the same keyed draws
        instead of taking their rows from the CPU."""
        self._cpu = ai  # (the numpy AI: it makes the town's flow field, and keeps the player out of the buildings)
        self.motions, self.cast, self.origin = ai.motions, ai.cast, np.asarray(ai.origin, np.float64).copy()
        self.seed, self.time, self.steps, self.substeps = ai.seed, ai.time, ai.steps, ai.substeps
        self.player = np.asarray(ai.player, np.float64).copy()
        self.config, self.half_extent = ai.config, ai.half_extent
        self.player_hits_taken = ai.player_hits_taken
        kinds, town = len(ai.motions), ai.obstacles is not None
        if getattr(self, "_kinds", None) != (kinds, town):
            self._programs = self._build_programs(kinds, town)
            self._kinds = (kinds, town)
        self._load_town(ai.obstacles)
        for name in ("_kind_block", "_pivots"):
            old = getattr(self, name, None)
            if old is not None:
                self._objects.remove(old)
                old.release()
        kinds_table, pivots = kind_table(ai), pivot_table(ai.motions)
        self._kind_block = self._objects.add(self.ctx.buffer(kinds_table.tobytes()))
        self._pivots = self._objects.add(self.ctx.buffer(pivots.tobytes()))
        self.sent_bytes += kinds_table.nbytes + pivots.nbytes
        self._any_attack = any(m.clip["attack"] >= 0 for m in ai.motions)
        self._allocate(ai.n)
        if fresh:
            first = cast_firsts(ai.cast)
            self._spawn(ai, [(k, int(first[k]), count) for k, count in enumerate(ai.cast)])
        else:
            for name, block in pack(ai).items():
                if ai.n:
                    self._state[name].write(block.tobytes())
                    self.sent_bytes += block.nbytes
                    if name == "motion":  # the foot lock's first run steps 0
                        self._ground.write(np.ascontiguousarray(block[:, :2]).tobytes())
                        self.sent_bytes += 8 * ai.n
        self.reset_counters()

    def _spawn(self, ai, runs) -> None:
        """Agents spawned anywhere on the GPU as the numpy AI `ai` just spawned them (crowd.sim.spawn), for
        `runs` of (character, first row, count): its seed, substep, step and start player are the keys."""
        runs = [(k, first, count) for k, first, count in runs if count]
        if not runs:
            return
        program, cfg = self._programs["spawn"], ai.config
        self._bind()
        self._ground.bind_to_storage_buffer(GROUND)
        base = lambda purpose: self._base(purpose, ai.seed, ai.substeps)  # noqa: E731
        values = dict(u_steps=ai.steps, u_health=int(cfg.health), u_half=self._half32(ai.half_extent),
                      u_player=tuple(float(v) for v in ai.start_player - self.origin), u_start_clear=cfg.start_clear,
                      u_base_traits=base(_TRAITS), u_base_looks=base(_LOOKS), u_base_arms=base(_ARMS),
                      u_speed=(cfg.speed_min, cfg.speed_max), u_reaction=(cfg.reaction_min, cfg.reaction_max),
                      u_runner_below=draw_bound(cfg.runner_share), u_armed_below=draw_bound(cfg.armed_share))
        if self.obstacles is not None:
            values.update(self._town_uniforms())
            self._field.bind_to_storage_buffer(FIELD)
        self._set(program, **values)
        program["u_base_place"].value = [base(_PLACE + attempt) for attempt in range(PLACE_TRIES)]
        program["u_tints"].value = [int(v) for v in np.concatenate([TINTS, np.full((len(TINTS), 1), 255, np.uint8)], axis=1).view(np.uint32)[:, 0]]
        for k, first, count in runs:
            m = ai.motions[k]
            self._set(program, u_first=first, u_count=count, u_kind=k, u_heads=max(m.head_count, 1), u_weapons=m.weapon_count,
                      u_weapon_first=m.weapon_first, u_walk_speed=m.walk_speed, u_run_speed=m.run_speed)
            program.run((count + GROUP - 1) // GROUP)
        self.ctx.memory_barrier(READ_BACK)

    def _load_town(self, obstacles) -> None:
        """The town's distance field (once) and an empty flow field; none of it without a town."""
        self.obstacles = obstacles
        if obstacles is None or getattr(self, "_field", None) is not None:
            self._flow_cell, self._flow_corner = None, (0.0, 0.0, 0.0)  # (a new crowd goes straight at the player until its field is in)
            return
        field = np.ascontiguousarray(obstacles.field, np.float32)
        self._field = self._objects.add(self.ctx.buffer(field.tobytes()))
        self._flow = self._objects.add(self.ctx.buffer(reserve=4 * FLOW_CELLS * FLOW_CELLS))
        self._field_n = field.shape[0] - 1
        self._flow_cell = None  # the cell of the flow field on the GPU
        self._flow_corner = (0.0, 0.0, 0.0)

    def _town_substep(self) -> dict:
        """Before a substep with a town: the numpy AI's share of its flow field's work, the field sent
        when one is published (37 KB, when the player has crossed a cell), and the town's uniforms."""
        ai = self._cpu
        ai.player = self.player
        ai._update_flow()
        if ai._flow_cell != self._flow_cell and ai._flow_corner[2]:
            steps = ai._flow_steps.astype(np.int32) + 2
            packed = (steps[0] | (steps[1] << 4) | (ai._flow_usable.astype(np.int32) << 8)).astype(np.uint32)
            self._flow.write(packed.tobytes())
            self.sent_bytes += packed.nbytes
            self._flow_cell = ai._flow_cell
            self._flow_corner = (float(ai._flow_corner[0] - self.origin[0]), float(ai._flow_corner[1] - self.origin[1]), 1.0)
        return self._town_uniforms()

    def _town_uniforms(self) -> dict:
        period = self.obstacles.period
        return dict(u_origin_mod=tuple(float(v) for v in np.mod(self.origin, period)), u_period=period, u_cell=self.obstacles.cell,
                    u_field_n=self._field_n, u_flow_corner=self._flow_corner)

    def resize_from(self, ai) -> None:
        """The crowd resized as the numpy AI `ai` just was (``CrowdAI.resize``: each character keeps its first
        agents, at its block's new place, ``ai.moved``): the kept agents' state copied on the GPU, the new
        ones spawned there from the keyed draws the numpy AI spawned them from."""
        old, old_ground = self._state, self._ground
        self._state, self._ground = {}, None  # (kept apart from _allocate's release)
        for buffer in (*old.values(), old_ground):
            self._objects.remove(buffer)
        try:
            self._allocate(ai.n)
            first = cast_firsts(ai.cast)
            for before, after, count in ai.moved:
                if count:
                    for name, buffer in self._state.items():
                        self.ctx.copy_buffer(buffer, old[name], 16 * count, 16 * before, 16 * after)
                    self.ctx.copy_buffer(self._ground, old_ground, 8 * count, 8 * before, 8 * after)
            self.cast, self.half_extent, self.config = ai.cast, ai.half_extent, ai.config
            self._spawn(ai, [(k, after + count, int(first[k + 1]) - after - count) for k, (_, after, count) in enumerate(ai.moved)])
        finally:
            for buffer in (*old.values(), old_ground):
                buffer.release()

    def _build_programs(self, kinds: int, town: bool = False) -> dict:
        for program in getattr(self, "_programs", {}).values():
            self._objects.remove(program)
            program.release()
        defines = {"KINDS": kinds, "SEPARATION_CELL_CAP": SEPARATION_CELL_CAP, **({"TOWN": 1} if town else {})}
        shader = lambda name, **extra: self._objects.add(self.ctx.compute_shader(load_shader(name, {**defines, **extra})))  # noqa: E731
        programs = {"think": shader("sim/think.comp.glsl", THINK_A=1), "finish": shader("sim/think.comp.glsl", FINISH=1),
                    "spawn": shader("sim/spawn.comp.glsl", PLACE_TRIES=PLACE_TRIES, TINT_COUNT=len(TINTS)),
                    "separation": shader("sim/separation.comp.glsl"), "layers": shader("sim/outputs.comp.glsl", LAYERS=1)}
        for name in ("HIT_LIST", "NEAREST_D", "NEAREST_I", "HIT_NEAREST", "LOOK_AT", "SWEEP", "COUNT", "PICK_T", "PICK_I"):
            programs[name] = shader("sim/hit.comp.glsl", **{name: 1})
        programs.update(foot=shader("sim/outputs.comp.glsl", FOOT_MOTION=1), overrides=shader("sim/outputs.comp.glsl", OVERRIDES=1),
                        override_list=shader("sim/outputs.comp.glsl", OVERRIDE_LIST=1))
        return programs

    def _allocate(self, n: int) -> None:
        """State buffers for n agents (at least one vec4 each: GL has no empty buffers)."""
        for buffer in self._state.values():
            self._objects.remove(buffer)
            buffer.release()
        self._state = {name: self._objects.add(self.ctx.buffer(reserve=max(16 * n, 16))) for name in (*_FIELD_NAMES, "scratch")}
        old = getattr(self, "_ground", None)
        if old is not None:
            self._objects.remove(old)
            old.release()
        self._ground = self._objects.add(self.ctx.buffer(reserve=max(8 * n, 8)))  # where each agent stood at the foot lock's last run
        if getattr(self, "_counters", None) is None:
            self._counters = self._objects.add(self.ctx.buffer(reserve=4 * COUNTER_WORDS))
        if n == 0 and getattr(self, "grid", None) is not None:
            self.grid.clear()
        self.n = n

    def download(self) -> dict[str, np.ndarray]:
        """Every agent's state under the numpy AI's names (synchronous: tests, a resize, a new crowd)."""
        blocks = {name: np.frombuffer(self._read(name), FIELDS[name][2]).reshape(self.n, 4) for name in FIELDS}
        return unpack(blocks, self.origin)

    def raw(self) -> dict[str, bytes]:
        """Every state buffer's bytes (the determinism test compares them)."""
        return {name: self._read(name) for name in (*FIELDS, "scratch")}

    def _read(self, name: str) -> bytes:
        return self._state[name].read(16 * self.n) if self.n else b""

    def store(self, ai) -> None:
        """Write the GPU's crowd into a numpy CrowdAI of the same agents (and its clock and counts: the
        blows landed, those at the load and the GPU's since)."""
        if ai.n != self.n:
            raise GpuAIError(f"a numpy AI of {ai.n} agents cannot hold the GPU's {self.n}")
        for name, array in self.download().items():
            getattr(ai, name)[...] = array
        ai.time, ai.steps, ai.substeps = self.time, self.steps, self.substeps
        ai.player, ai.player_hits_taken = self.player.copy(), self.player_hits_taken + self.read_counters()["blows"]
        ai._pairs = False
        ai._stale = True

    # -- a step

    def _bind(self) -> None:
        for name, (binding, _, _) in FIELDS.items():
            self._state[name].bind_to_storage_buffer(binding)
        self._state["scratch"].bind_to_storage_buffer(SCRATCH_BINDING)
        self._counters.bind_to_storage_buffer(COUNTERS)
        self._kind_block.bind_to_uniform_block(0)

    def _set(self, program, **values) -> None:
        set_uniforms(program, **values)

    def _base(self, purpose: int, seed: int | None = None, substeps: int | None = None) -> tuple[int, int]:
        """The keyed draws' base for this substep (or `substeps`) and purpose, as (low, high) 32-bit halves."""
        seed, substeps = self.seed if seed is None else seed, self.substeps if substeps is None else substeps
        base = (seed * 0x9E3779B97F4A7C15 + substeps * 0xD1B54A32D192ED03 + purpose * 0xAEF17502108EF2D9) & _MASK64
        return base & 0xFFFFFFFF, base >> 32

    def step(self, dt: float) -> int:
        """Advance by dt seconds (clamped to max_dt) in equal substeps, as the numpy AI does. Returns the
        substep count. The blows that landed are counted on the GPU (``read_counters``)."""
        if isinstance(dt, bool) or not isinstance(dt, (int, float, np.floating)) or not math.isfinite(dt) or dt < 0:
            raise GpuAIError(f"dt must be a finite number >= 0, got {dt!r}")
        dt = min(float(dt), self.config.max_dt)
        if self.obstacles is not None:  # a player put in a building is chased to the street beside it (the numpy AI's rule)
            self.player = np.concatenate(self._cpu.keep_out(self.player[:1], self.player[1:]))
        count = self.config.substeps_for(dt)
        for _ in range(count):
            self._substep(dt / count)
        self.steps += 1
        return count

    def _half32(self, half_extent: float | None = None) -> float:
        """The world's half width as float32 no larger than the float64 one: an agent the GPU clamps to it is
        inside the world in float64 too."""
        exact = self.half_extent if half_extent is None else half_extent
        half = np.float32(exact)
        return float(np.nextafter(half, np.float32(0)) if float(half) > exact else half)

    def _timed(self, name: str):
        return self.timer.gpu(name) if self.timer is not None else contextlib.nullcontext()

    def _substep(self, h: float) -> None:
        self.time += h
        if not self.n:  # (as the numpy twin: an empty crowd's substep draws nothing and counts nothing)
            return
        cfg, p = self.config, self._programs
        self._bind()
        groups = (self.n + GROUP - 1) // GROUP
        player = tuple(float(v) for v in self.player - self.origin)
        grown = cfg.alert(self.time)
        common = dict(u_n=self.n, u_h=h, u_player=player, u_half=self._half32(), u_steps=self.steps)
        if self.obstacles is not None:
            common.update(self._town_substep())
            self._field.bind_to_storage_buffer(FIELD)
            self._flow.bind_to_storage_buffer(FLOW)
        self._set(p["think"], **common, u_base_respawn=self._base(_RESPAWN), u_base_wander=self._base(_WANDER),
                  u_notice=cfg.notice_radius + grown, u_forget=cfg.forget_radius + grown, u_reach=cfg.attack_reach,
                  u_cooldown=cfg.attack_cooldown, u_corpse_time=cfg.corpse_time, u_wander_radius=cfg.wander_radius,
                  u_wander_speed=cfg.wander_speed, u_arrive=cfg.arrive_distance, u_max_accel=cfg.max_accel, u_health=int(cfg.health))
        with self._timed("ai_think"):
            p["think"].run(groups)
            self.ctx.memory_barrier(SHADER_STORAGE)
        if cfg.separation_stiffness > 0.0:  # (no grid without separation)
            self._separate(h)
        self._pivots.bind_to_storage_buffer(PIVOTS)
        if self.obstacles is not None:  # (the grid used these bindings)
            self._field.bind_to_storage_buffer(FIELD)
            self._flow.bind_to_storage_buffer(FLOW)
        step = cfg.turn_rate * h
        self._set(p["finish"], **common, u_cos_step=math.cos(step), u_sin_step=math.sin(step), u_plant_feet=bool(cfg.plant_feet))
        with self._timed("ai_finish"):
            p["finish"].run(groups)
            self.ctx.memory_barrier(READ_BACK)
        self.substeps += 1

    def _separate(self, h: float) -> None:
        """The grid of the living and each one's push from it (the finish pass adds it)."""
        cfg, groups = self.config, (self.n + GROUP - 1) // GROUP
        radii = kind_radii(cfg.separation_radius, self.motions)  # (each character's: its footprint's)
        r = float(radii.max())
        # The numpy twin's cells (2r, or wider where that would be over 4 cells an agent), so that its cap
        # of candidates a row of cells means the same: wider cells would drop real neighbours in a pile-up.
        size, side = grid_shape(self.half_extent, 2.0 * r, self.n)
        self.grid.build(self._state["motion"], self.n, (-self.half_extent, -self.half_extent), size, side, self.timer)
        self._bind()
        self._set(self._programs["separation"], u_side=side, u_cells=side * side, u_radius=radii.astype(np.float32).tobytes(),
                  u_gain=min(cfg.separation_stiffness * h, 1.0))
        with self._timed("ai_separation"):
            self._programs["separation"].run(groups)
            self.ctx.memory_barrier(SHADER_STORAGE)

    # -- outputs

    def write_layers(self, out: moderngl.Buffer, first: int = 0) -> None:
        """The processor's (N, 4, 4) float32 layers, written into `out` from agent row `first` on."""
        if out.size < 64 * (first + self.n):
            raise GpuAIError(f"a layer buffer of {out.size} bytes cannot hold {self.n} agents' layers from row {first}")
        if not self.n:
            return
        self._bind()
        out.bind_to_storage_buffer(LAYERS_OUT)
        self._set(self._programs["layers"], u_n=self.n, u_first=int(first), u_fade_len=max(self.config.crossfade, 1e-6))
        with self._timed("ai_layers"):
            self._programs["layers"].run((self.n + GROUP - 1) // GROUP)
            self.ctx.memory_barrier(READ_BACK)  # (the processor's texture copies from it next)

    def layers(self) -> np.ndarray:
        """The layers as a numpy array (synchronous: tests)."""
        buffer = self.ctx.buffer(reserve=max(64 * self.n, 64))
        try:
            self.write_layers(buffer)
            return np.frombuffer(buffer.read(64 * self.n), np.float32).reshape(self.n, 4, 4).copy()
        finally:
            buffer.release()

    # -- the player's blows

    def _hit_pass(self, name: str, groups: int, bind: bool = True, **values) -> None:
        """One pass over the crowd's buffers; `bind` False: straight after another such pass (bound)."""
        if bind:
            self._bind()
        self._set(self._programs[name], u_n=self.n, **values)
        self._programs[name].run(max(groups, 1))
        self.ctx.memory_barrier(READ_BACK)

    def reset_counters(self) -> None:
        """Every count to zero (a new crowd), both nearest searches to none."""
        words = np.zeros(COUNTER_WORDS, np.uint32)
        words[12:14] = 0x7F800000  # nearest distances: +inf until a search finds one
        words[14:16] = 0xFFFFFFFF
        words[19] = 0xFFFFFFFF
        words[PICK_WORD:PICK_WORD + 2] = 0x7F800000, 0xFFFFFFFF
        self._counters.write(words.tobytes())
        self.sent_bytes += words.nbytes

    def read_counters(self) -> dict:
        """The counters as they stand (synchronous: tests; the pipeline reads copies through its ring,
        crowd.sim.gpu.facts)."""
        return facts_of(self._counters.read())

    @property
    def places(self) -> moderngl.Buffer:
        """The agents' (x, z, vx, vz) float32, from the origin (agents.glsl's Motion), for passes that
        read where each one stands."""
        return self._state["motion"]

    @property
    def looks(self) -> moderngl.Buffer:
        """The agents' (tint, head, weapon + 1, spawned step) uint32 (agents.glsl's Looks)."""
        return self._state["looks"]

    @property
    def counters(self) -> moderngl.Buffer:
        return self._counters

    def hit(self, agents) -> None:
        """The player strikes these agents (the numpy AI's ``hit``: unknown numbers and the dead ignored)."""
        idx = np.unique(np.asarray(agents, np.int64).reshape(-1))
        idx = idx[(idx >= 0) & (idx < self.n)].astype(np.int32)
        if not idx.size:
            return
        targets = self.ctx.buffer(idx.tobytes())
        self.sent_bytes += idx.nbytes
        try:
            targets.bind_to_storage_buffer(LAYERS_OUT)
            self._hit_pass("HIT_LIST", (idx.size + GROUP - 1) // GROUP, u_count=int(idx.size))
        finally:
            targets.release()

    def _nearest(self, search: int, point, reach: float) -> dict:
        self._counters.write(np.array([0x7F800000], np.uint32).tobytes(), offset=4 * (12 + search))
        self._counters.write(np.array([0xFFFFFFFF], np.uint32).tobytes(), offset=4 * (14 + search))
        self.sent_bytes += 8
        values = dict(u_point=tuple(float(v) for v in np.asarray(point, np.float64) - self.origin), u_reach=float(reach), u_search=search)
        groups = (self.n + GROUP - 1) // GROUP
        self._hit_pass("NEAREST_D", groups, **values)
        self._hit_pass("NEAREST_I", groups, bind=False, **values)
        return values

    def strike_nearest(self, point, reach: float) -> None:
        """Hit the nearest living agent within `reach` of a ground point (x, z), on the GPU (the numpy
        twin: ``hit([nearest_alive(point, reach)])``); which one, if any, comes back in the counters."""
        if self.n:
            self._hit_pass("HIT_NEAREST", 1, bind=False, **self._nearest(STRIKE, point, reach))

    def look(self, point, reach: float) -> None:
        """Find the nearest living agent within `reach` of a ground point and note where it stands (the
        numpy twin: ``nearest_alive``): a survivor keeps the nearest threat in front; it comes back in
        the counters."""
        if self.n:
            self._hit_pass("LOOK_AT", 1, bind=False, **self._nearest(LOOK, point, reach))

    def pick(self, origin, direction, radius: float, height: float, serial: int) -> None:
        """Find the agent a ray (world origin, unit direction) enters first, through each agent's upright
        cylinder of `radius` and `height` times its scale: its answer to request `serial` is in the counters,
        and so in the facts read back N frames later (``facts_of``'s "picked"). Nothing waits for it."""
        self._counters.write(np.array([0x7F800000, 0xFFFFFFFF, serial], np.uint32).tobytes(), offset=4 * PICK_WORD)
        self.sent_bytes += 12
        if not self.n:
            return
        rel = np.asarray(origin, np.float64) - np.array([self.origin[0], 0.0, self.origin[1]])
        values = dict(u_ray_origin=tuple(float(v) for v in rel), u_ray_dir=tuple(float(v) for v in direction), u_pick_radius=float(radius),
                      u_pick_height=float(height))
        groups = (self.n + GROUP - 1) // GROUP
        self._hit_pass("PICK_T", groups, **values)
        self._hit_pass("PICK_I", groups, bind=False, **values)

    def sweep(self, point, reach: float, front) -> None:
        """Hit every living agent within `reach` of a ground point on the side `front` faces (the numpy
        twin: ``hit(alive_in_front(point, reach, front))``)."""
        if self.n:
            self._hit_pass("SWEEP", (self.n + GROUP - 1) // GROUP, u_point=tuple(float(v) for v in np.asarray(point, np.float64) - self.origin),
                           u_reach=float(reach), u_front=tuple(float(v) for v in front))

    def count_states(self, point=None, reach: float = 0.0, selected: int = -1) -> None:
        """Count the agents in each state into the counters (the HUD's and the stats' counts), the living
        within `reach` of a ground `point` (the HUD's), and copy out the `selected` agent's row (the panel's)."""
        self._counters.write(bytes(32), offset=16)
        self._counters.write(np.array([0, -1], np.int32).tobytes(), offset=72)
        self.sent_bytes += 40
        if self.n:
            rel = (0.0, 0.0) if point is None else tuple(float(v) for v in np.asarray(point, np.float64) - self.origin)
            self._hit_pass("COUNT", (self.n + GROUP - 1) // GROUP, u_point=rel, u_reach=float(reach), u_selected=int(selected))

    def counts(self) -> dict[str, int]:
        """Agents in each state (synchronous: tests and benchmarks)."""
        self.count_states()
        return self.read_counters()["states"]

    # -- what the frame's later stages get

    def write_foot_motion(self, targets) -> None:
        """The foot lock's motion (crowd.agent_rows.FootLockSteps' twin) into each (first agent, agents,
        buffer) of `targets` (AnimationProcessor.lock_motion_targets), for the crowd's agents among them."""
        if not self.n:
            return
        self._bind()
        self._ground.bind_to_storage_buffer(GROUND)
        p = self._programs["foot"]
        for first, count, buffer in targets:
            count = min(count, self.n - first)
            if count <= 0:
                continue
            buffer.bind_to_storage_buffer(LAYERS_OUT)
            self._set(p, u_n=self.n, u_first=int(first), u_count=int(count))
            p.run((count + GROUP - 1) // GROUP)
        self.ctx.memory_barrier(READ_BACK)

    def apply_overrides(self, layers: moderngl.Buffer, overrides, time: float, clip: tuple, within: slice | None) -> int:
        """A person's overrides (crowd.frame.LayerOverrides) on top of the layers in `layers`, on the GPU;
        `clip`: the forced clip's (duration, speed, loop); `within`: its character's agents (None: all).
        Returns the bytes sent (a list of agents, where the overrides name some)."""
        if not overrides or not self.n:
            return 0
        forced = overrides.forced
        lo, hi = (0, self.n) if within is None else (within.start, min(within.stop, self.n))
        held_all, held_listed = np.full(4, -1.0), np.full(4, -1.0)
        flags: dict[int, int] = {}
        for layer, (weight, agents) in overrides.held.items():
            if agents is None:
                held_all[layer] = weight
            else:
                held_listed[layer] = weight
                for a in np.asarray(agents, np.int64).reshape(-1):
                    flags[int(a)] = flags.get(int(a), 0) | (1 << layer)
        if forced is not None and forced.agents is not None:
            for a in np.asarray(forced.agents, np.int64).reshape(-1):
                flags[int(a)] = flags.get(int(a), 0) | 16
        values = dict(u_n=self.n, u_lo=lo, u_hi=hi, u_forced_all=forced is not None and forced.agents is None,
                      u_forced_clip=float(forced.clip if forced is not None else 0), u_held_all=tuple(held_all), u_held_listed=tuple(held_listed),
                      u_forced_phase=float(overrides.forced_phase(time, *clip)))
        self._bind()
        layers.bind_to_storage_buffer(LAYERS_OUT)
        self._set(self._programs["overrides"], **values)
        self._programs["overrides"].run((self.n + GROUP - 1) // GROUP)
        self.ctx.memory_barrier(READ_BACK)
        if not flags:
            return 0
        entries = np.array(sorted(flags.items()), np.int32)
        buffer = self.ctx.buffer(entries.tobytes())
        self.sent_bytes += entries.nbytes
        try:
            buffer.bind_to_storage_buffer(ENTRIES)
            self._set(self._programs["override_list"], **values, u_entries=len(entries))
            self._programs["override_list"].run((len(entries) + GROUP - 1) // GROUP)
            self.ctx.memory_barrier(READ_BACK)
        finally:
            buffer.release()
        return entries.nbytes

    def frame_output(self, extra=None, max_scale: float = 1.08) -> SimFrame:
        """This frame's SimFrame (crowd.frame): the state buffers the later stages read."""
        return SimFrame(self.n, tuple(self.cast), dict(self._state), self.origin.copy(), self.steps, extra, max_scale)

    def gpu_bytes(self) -> dict[str, int]:
        """Bytes of the AI's buffers: the agents' state, and the grid."""
        state = sum(b.size for b in self._state.values()) + self._counters.size + self._kind_block.size + self._pivots.size
        return {"ai_state": state, "ai_grid": self.grid.gpu_bytes()}

    def release(self) -> None:
        if hasattr(self, "_objects"):
            self._objects.release()
        self._state = {}
