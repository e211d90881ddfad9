"""Simulate stage: the crowd AI. Every agent is a row in a few numpy arrays, stepped without a
per-agent Python loop.

Contract: ``CrowdAI(agents, seed, motion, config)``; per frame ``step(dt)``, then ``instances()``
(render input) and ``write_layers(out)`` (the processor's (N, 4, 4) input, written in place).
A crowd of several characters: ``CrowdAI(agents, seed, motions, config, shares=...)``, one Motion per
character; each character's agents are one block, in the cast's order (crowd.frame.cast_counts), and
each agent moves and animates with its own character's clips, strides and speeds.
``hit(agents)`` is how the player strikes; ``player`` is a float64 point on the ground (x, z) that
the window moves, or that ``PlayerScript`` walks in headless mode.

Behaviour, per agent: wander between random points (pausing now and then) until the player comes
within ``notice_radius``; after the agent's reaction delay, shamble or run toward the player (runners
run), slow down on arrival and attack in reach. A hit plays the hit reaction; the last hit plays
death, the body lies still for ``corpse_time`` and the agent respawns at an edge of the world.

Animation choice: layers 0-2 are idle, walk and run, weighted by ground speed and sharing one phase
that advances by speed over the blended stride length, so feet do not slide; layer 3 is the action
(attack, hit, death), faded in and out over ``crossfade`` seconds. An attack plays on the upper body
through the skeleton's joint mask; hit and death play on the whole body.

Stability: dt is clamped to ``max_dt`` and stepped in equal substeps of at most ``substep``. Positions
are float64; the renderer subtracts the camera before anything becomes float32.

This module holds ``CrowdAI``'s core (the agents' arrays, the player's blows, the step) and the
headless ``PlayerScript``; CrowdAI's other parts are mixed in from a module each: spawn, think,
think_budget, separation (neighbours from a uniform grid), obstacles (the town and its flow field),
workers (several cores) and outputs (layers, instances). config holds the settings and the states,
motion and locomotion what the AI knows of the clips and how it blends them. Their public names are
importable from here too.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..frame import FrameError, cast_counts, cast_firsts, cast_moves
from .agent_pool import PARAMS, AgentPool, SharedArrays
from .config import ACT_DEATH, ACT_HIT, ACTION_ROLES, CHASE, DYING, HIT, LAYERS, NO_ACTION, WANDER, AIConfig, AIError
from .locomotion import _KIND_FIELDS, _AgentMotion
from .motion import Motion
from .obstacles import _FLOW_ARRAYS, FLOW_CELLS, ObstaclesMixin
from .outputs import OutputsMixin
from .separation import SeparationMixin
from .spawn import SpawnMixin
from .think import ThinkMixin
from .think_budget import ThinkBudgetMixin
from .workers import (APPLY, FINISH, MAX_FOCUS, P_BLOCK, P_FOCUS, P_FOCUS_COUNT, P_GAIN, P_H, P_HAVE_PAIRS, P_PLAYER, P_REBUILD, P_STEPS,
                      P_SUBSTEPS, P_TIME, PUSH, THINK, WorkersMixin)


TOWN_CIRCLE_M = 9.0  # the headless player's circle in a town: round the crossing, clear of the buildings at its corners


class PlayerScript:
    """The headless player: walks a circle through the crowd and strikes the nearest zombie in reach at
    a steady rhythm; a survivor faces the nearest zombie within WATCH_M as it goes, as a player keeps
    the threat in front. Deterministic: it depends on time and the crowd only."""

    WATCH_M = 4.0

    def __init__(self, radius: float, speed: float = 2.4, strike_every: float = 0.9, strike_reach: float = 2.0):
        self.radius = float(radius)
        self.speed = float(speed)
        self.strike_every = float(strike_every)
        self.strike_reach = float(strike_reach)
        self._next_strike = self.strike_every

    @classmethod
    def headless(cls, ai: "CrowdAI") -> "PlayerScript":
        """The headless loop's player in `ai`'s world: a circle half way to the edge through the horde, or in
        a town round the crossing at the centre, in its streets."""
        half = ai.half_extent * 0.5
        return cls(half if ai.obstacles is None else min(half, TOWN_CIRCLE_M))

    def update(self, ai: "CrowdAI", survivor=None) -> None:
        """Move the player along its circle and strike on the beat: the AI's player point itself, or,
        with a `survivor` (crowd.sim.player), that character, told to run to the circle's point and to
        swing (its blow lands when the swing does)."""
        t = ai.time
        angle = t * self.speed / max(self.radius, 1e-3)
        point = ai.origin + self.radius * np.array([math.cos(angle), math.sin(angle)])
        if survivor is not None:
            near = ai.nearest_threat(survivor.position, self.WATCH_M)
            threat = None if near is None else near - survivor.position
            survivor.walk_to(point, threat if threat is not None and float(np.hypot(*threat)) > 1e-6 else None)
        else:
            ai.player = point
        while t >= self._next_strike:
            self._next_strike += self.strike_every
            if survivor is not None:
                survivor.strike()
                continue
            ai.strike_nearest(ai.player, self.strike_reach)


class CrowdAI(SpawnMixin, ThinkMixin, ThinkBudgetMixin, SeparationMixin, ObstaclesMixin, WorkersMixin, OutputsMixin):
    def __init__(self, agents: int, seed: int, motion, config: AIConfig | None = None, origin=(0.0, 0.0), shares=None,
                 obstacles=None):
        """`motion`: a Motion, or one per character of a cast, whose `shares` (as many, each above 0;
        default equal) say how much of the crowd each character is. `obstacles`: where the crowd cannot
        walk (crowd.asset.town.Obstacles), or None for open ground."""
        self.config = (config or AIConfig()).validate()
        self.obstacles = obstacles
        self._flow_job = None  # (cell, its flow_field_work) while a field is being made: see _update_flow
        self._flow_cell = None  # the cell of the field in the shared arrays
        motions = (motion,) if isinstance(motion, Motion) else tuple(motion)
        shares = (1.0,) * len(motions) if shares is None else tuple(shares)
        if not motions or len(shares) != len(motions):
            raise AIError(f"a cast needs a share per character: {len(motions)} characters, {len(shares)} shares")
        try:
            cast_counts(0, shares)
        except FrameError as exc:
            raise AIError(str(exc)) from None
        self.motions, self.shares = motions, tuple(float(x) for x in shares)
        self.cast = (0,) * len(motions)  # agents of each character, in the cast's order
        self._kind_fields = _KIND_FIELDS if len(motions) > 1 else ()
        self.seed = int(seed)
        origin = np.asarray(origin, np.float64)
        if origin.shape != (2,) or not np.all(np.isfinite(origin)):
            raise AIError("AI origin must be a finite (x, z) pair")
        self.origin = origin  # float64 centre of the world square
        self.time = 0.0
        self.player = origin.copy()
        self.start_player = origin.copy()  # where the player stood at the last spawn anywhere (its clearance's centre)
        self.player_hits_taken = 0
        self.steps = 0  # step() calls so far; an agent's spawned_step is the step in which it (re)appeared
        self.pair_builds = 0  # how often the separation's neighbour list was rebuilt (benchmarks report it)
        self.separation_seconds = 0.0  # CPU time spent in separation so far: what bounds a big crowd's step
        self.substeps = 0  # substeps so far: the think budget's block of the next one is substeps % think_every
        self.focus: tuple = ()  # ground points (x, z) besides the player near which agents think every substep: the camera
        self._layer_template: dict = {}  # per character: (clip indices, write_layers' constant columns for a run of agents)
        self._motion_tables()
        self._pool: AgentPool | None = None  # worker processes, started when a crowd is big enough to split
        self._block: SharedArrays | None = None  # the agents' arrays while the pool steps them
        self._grid_block: SharedArrays | None = None  # where each grid cell's agents start, for the list's builds
        self._params = np.zeros(PARAMS)  # a phase's numbers (the pool's shared ones while it runs)
        self._respawns = 0  # agents respawned by this process's range in a phase
        self.n = 0
        self._allocate(0)
        self.resize(agents)

    @property
    def motion(self) -> Motion:
        """The first character's Motion (the only one in a crowd of one character)."""
        return self.motions[0]

    def _motion_tables(self) -> None:
        """Per character (rows) and action code: lengths and clips, for one gather per step (NO_ACTION
        never ends by time); which roles each has; the values the locomotion reads per agent."""
        ms = self.motions
        self._action_length = np.array([[np.inf] + [m.duration[r] if m.clip[r] >= 0 else np.inf for r in ACTION_ROLES[1:]] for m in ms])
        self._action_clip = np.array([[0] + [max(m.clip[r], 0) for r in ACTION_ROLES[1:]] for m in ms], np.float32)
        self._role_clip = {role: np.array([m.clip[role] for m in ms]) for role in ("attack", "hit", "death")}
        self._upper_mask = np.array([m.upper_body_mask for m in ms], np.float32)
        self._per_kind = {"_m_walk_stride": np.array([m.walk_stride for m in ms]), "_m_run_stride": np.array([m.run_stride for m in ms]),
                          "_m_run_speed": np.array([m.run_speed for m in ms]), "_m_walk_slowest": np.array([m.walk_slowest for m in ms]),
                          "_m_idle": np.array([m.duration["idle"] for m in ms], np.float64)}
        self._walk_speed = np.array([m.walk_speed for m in ms])
        self._run_speed = np.array([m.run_speed for m in ms])

    def _fill_kind_fields(self) -> None:
        """Each agent's copy of its character's locomotion values (a cast of several characters)."""
        for name in self._kind_fields:
            getattr(self, name)[:] = self._per_kind[name][self.kind]

    def _m(self, a=None, agents=None):
        """The motion the locomotion functions take for the agents of `a` (the crowd, or a think's
        agents; `agents`: indices into it): the Motion itself for one character (scalars), else the
        agents' own values."""
        if not self._kind_fields:
            return self.motions[0]
        a = self if a is None else a
        pick = (lambda name: getattr(a, name)) if agents is None else (lambda name: getattr(a, name)[agents])
        return _AgentMotion(pick("_m_walk_stride"), pick("_m_run_stride"), pick("_m_run_speed"), pick("_m_walk_slowest"), {"idle": pick("_m_idle")})

    def _kind_of(self, a, agents=None):
        """The character (row of the per-character tables) of agents of `a`: 0 for a crowd of one."""
        if not self._kind_fields:
            return 0
        return a.kind if agents is None else a.kind[agents]

    def action_length(self, action: np.ndarray, kind=0) -> np.ndarray:
        """Seconds an action lasts (inf for none), per agent, for agents of characters `kind`."""
        return self._action_length[0][action] if np.ndim(kind) == 0 and kind == 0 and len(self.motions) == 1 else self._action_length[kind, action]

    def set_motion(self, motion: Motion, kind: int = 0) -> None:
        """New clips, durations or speeds for one character (a re-bake, a clip's playback speed): every
        agent keeps its state and its speed factor; top speeds follow the new locomotion speeds."""
        motions = list(self.motions)
        motions[kind] = motion
        self.motions = tuple(motions)
        self._motion_tables()
        self._fill_kind_fields()
        self._stale = True
        first = cast_firsts(self.cast)
        part = slice(int(first[kind]), int(first[kind + 1]))
        self.walk_top[part] = motion.walk_speed * self.speed_factor[part]
        self.chase_top[part] = np.where(self.runner[part], motion.run_speed, motion.walk_speed) * self.speed_factor[part]

    def set_config(self, config: AIConfig) -> None:
        """New AI settings at run time (the panel): the world size follows the new settings."""
        config = config.validate()
        if self._pool is not None and config.workers != self.config.workers:
            self._stop_pool()  # restarted at its new size when a substep needs it
        self.config = config
        self.half_extent = self.config.half_extent_for(self.n, self._free_share())
        self._pairs = False
        self._stale = True
        self._exact[:] = self._must_be_exact(self)  # a new budget, or none: everyone starts from now
        self._pending[:] = 0.0
        self._bound(0, self.n)

    # -- agents (one numpy array per attribute; x and z apart so the hot loop reads contiguous memory)

    _FLOAT = ("x", "z", "vx", "vz", "hx", "hz", "state_time", "aware", "tx", "tz", "pause", "phase", "action_time", "cooldown",
              "speed_factor", "reaction", "walk_top", "chase_top",
              "phase_rate", "_pending",  # the think budget's: the phase's rate between thinks, the time since the last,
              "_goal_x", "_goal_z")  # and the heading a far agent turns toward between thinks
    _OTHER = {"state": np.int8, "action": np.int8, "health": np.int16, "runner": bool, "scale": np.float32, "head": np.int32,
              "weapon": np.int16, "kind": np.int8,  # kind: the agent's character, the cast's index
              "spawned_step": np.int64,
              "_exact": bool,  # thinks every substep (the think budget)
              "_coast_turn": bool}  # turns toward its goal heading between thinks

    def _layout(self, n: int) -> dict:
        """Every per-agent array, name -> (dtype, shape): the agents' state (``_names``), the neighbour
        list's per-agent part and the layers write_layers fills."""
        layout = {name: (np.float64, (n,)) for name in (*self._FLOAT, *self._kind_fields)}
        layout.update({name: (dtype, (n,)) for name, dtype in self._OTHER.items()})
        layout["tint"] = (np.uint8, (n, 4))
        layout.update(_cell=(np.int64, (n,)), _cell_order=(np.intp, (n,)),  # the grid of the neighbour lists' last build
                      _pairs_x=(np.float64, (n,)), _pairs_z=(np.float64, (n,)),  # where the agents stood at it
                      _layer_out=(np.float32, (n, LAYERS, 4)), _yaw_out=(np.float32, (n,)))
        if self.obstacles is not None:  # the published flow field (_update_flow), which every process reads
            layout.update(_flow_steps=(np.int8, (2, FLOW_CELLS, FLOW_CELLS)), _flow_usable=(bool, (FLOW_CELLS, FLOW_CELLS)),
                          _flow_corner=(np.float64, (3,)))  # x, z, and 1 once a field is in
        return layout

    def _allocate(self, n: int):
        """Zeroed arrays for n agents, in shared memory while worker processes step the crowd. Returns the
        block the arrays were in before, if any (the caller copies from it, then closes it)."""
        was = self._block
        layout = self._layout(n)
        if self._grid_block is not None:  # sized for the old crowd: the next build makes one to fit
            self._grid_block.close()
            self._grid_block = None
        if self._pool is not None:
            self._block = SharedArrays(layout)
            arrays = self._block.arrays
        else:
            self._block = None
            arrays = {name: np.zeros(shape, dtype) for name, (dtype, shape) in layout.items()}
        for name, array in arrays.items():
            setattr(self, name, array)
        self._pairs = False  # the separation's neighbour lists are to be built (see _prepare_lists)
        self._range_list = None  # this process's range's list (see _build_list)
        self._cell_first = np.zeros(1, np.int64)
        self._stale = True
        return was

    def _names(self):
        return (*self._FLOAT, *self._kind_fields, *self._OTHER, "tint")

    @property
    def pos(self) -> np.ndarray:
        """(N, 2) float64 ground positions (x, z); a copy."""
        return np.stack([self.x, self.z], axis=1)

    @property
    def yaw(self) -> np.ndarray:
        """Heading about +Y in radians: the agent's front is (sin yaw, cos yaw) in (x, z)."""
        return np.arctan2(self.hx, self.hz)

    def resize(self, agents: int) -> None:
        """Change the agent count at run time: each character keeps its first agents, with their state
        (at their character's new place in a cast of several: crowd.frame.cast_moves), new ones spawn."""
        if isinstance(agents, bool) or not isinstance(agents, (int, np.integer)) or agents < 0:
            raise AIError(f"agent count must be a whole number >= 0, got {agents!r}")
        n = int(agents)
        cast = cast_counts(n, self.shares)
        moves = cast_moves(self.cast, cast)
        self.half_extent = self.config.half_extent_for(n, self._free_share())
        kept = {name: [getattr(self, name)[before:before + count] for before, _, count in moves] for name in self._names()}
        flow = {name: getattr(self, name).copy() for name in _FLOW_ARRAYS} if self.obstacles is not None else {}
        was = self._allocate(n)
        for name, array in flow.items():  # the published flow field stays (it is the player's, not the agents')
            getattr(self, name)[...] = array
        for name, blocks in kept.items():
            array = getattr(self, name)
            for (_, after, count), block in zip(moves, blocks):
                array[after:after + count] = block
        del kept
        if was is not None:
            was.close()
        self.n, self.cast = n, cast
        first = cast_firsts(cast)
        for k in range(len(cast)):
            self.kind[first[k]:first[k + 1]] = k
        self._fill_kind_fields()
        fresh = np.concatenate([np.arange(after + count, first[k + 1]) for k, (_, after, count) in enumerate(moves)]).astype(np.int64)
        self._spawn(self, fresh, anywhere=True)
        self._exact[fresh] = self._must_be_exact(self)[fresh]
        self.moved = moves  # where each character's kept agents went (the pipeline moves its per-agent state alike)
        # Agents outside a shrunken world are brought inside by the next step's bounds.

    # -- player actions

    def alive(self) -> np.ndarray:
        return self.state < DYING

    def steady(self, agents: np.ndarray) -> np.ndarray:
        """Whether each of `agents` is in plain locomotion: wandering or chasing, playing no action (the
        foot-skate sample asks for its few agents only)."""
        state = self.state[agents]
        return (self.action[agents] == NO_ACTION) & ((state == WANDER) | (state == CHASE))

    def armed(self) -> np.ndarray:
        """Living agents holding a weapon (a dying one has dropped it)."""
        return (self.weapon >= 0) & (self.state < DYING)

    def nearest_alive(self, point, reach: float) -> int:
        """Index of the nearest living agent within `reach` of a ground point (x, z), or -1."""
        if not self.n:
            return -1
        px, pz = (float(v) for v in point)
        d = np.sqrt((self.x - px) ** 2 + (self.z - pz) ** 2)
        d[~self.alive()] = np.inf
        i = int(np.argmin(d))
        return i if d[i] <= reach else -1

    def nearest_threat(self, point, reach: float) -> np.ndarray | None:
        """Where the nearest living agent within `reach` of a ground point stands (x, z), or None."""
        i = self.nearest_alive(point, reach)
        return None if i < 0 else np.array([self.x[i], self.z[i]])

    def strike_nearest(self, point, reach: float) -> int:
        """The player's blow on the nearest living agent within `reach` of a ground point: returns it, or -1."""
        target = self.nearest_alive(point, reach)
        if target >= 0:
            self.hit(np.array([target]))
        return target

    def alive_in_front(self, point, reach: float, front) -> np.ndarray:
        """Indices of the living agents within `reach` of a ground point (x, z), on the side `front`
        (x, z) faces: what a swing there sweeps."""
        if not self.n:
            return np.zeros(0, np.int64)
        px, pz = (float(v) for v in point)
        fx, fz = (float(v) for v in front)
        dx, dz = self.x - px, self.z - pz
        return np.flatnonzero((dx * dx + dz * dz <= reach * reach) & (dx * fx + dz * fz >= 0.0) & self.alive())

    def hit(self, agents) -> int:
        """The player strikes these agents: the last hit kills (where there is a death clip), others
        play the hit reaction. Dead or dying agents and unknown indices are ignored. Returns how many
        the blow killed."""
        idx = np.unique(np.asarray(agents, np.int64).reshape(-1))
        idx = idx[(idx >= 0) & (idx < self.n)]
        idx = idx[self.alive()[idx]]
        if not idx.size:
            return 0
        kind = self.kind[idx]
        self.health[idx] -= (self._role_clip["death"][kind] >= 0).astype(np.int16)  # without a death clip, a zombie does not die
        dying = idx[self.health[idx] <= 0]
        hurt = idx[self.health[idx] > 0]
        self._start(dying, DYING, ACT_DEATH)
        self._start(hurt[self._role_clip["hit"][self.kind[hurt]] >= 0], HIT, ACT_HIT)
        self.aware[hurt] = np.maximum(self.aware[hurt], self.reaction[hurt])  # a hit agent knows where the player is
        self._exact[idx] = True  # a hit is exact from the next substep on, whatever the budget
        self._pending[idx] = 0.0
        return int(dying.size)

    def _start(self, idx: np.ndarray, state: int, action: int, a=None) -> None:
        """Agents `idx` of `a` (the agents of one think; by default the crowd) start an action."""
        a = self if a is None else a
        a.state[idx] = state
        a.state_time[idx] = 0.0
        a.action[idx] = action
        a.action_time[idx] = 0.0

    # -- stepping

    def step(self, dt: float) -> int:
        """Advance by dt seconds (clamped to max_dt) in equal substeps. Returns the substep count."""
        if isinstance(dt, bool) or not isinstance(dt, (int, float, np.floating)) or not math.isfinite(dt) or dt < 0:
            raise AIError(f"dt must be a finite number >= 0, got {dt!r}")
        dt = min(float(dt), self.config.max_dt)
        if self.obstacles is not None:  # a player put in a building is chased to the street beside it
            self.player = np.concatenate(self.keep_out(self.player[:1], self.player[1:]))
        count = self.config.substeps_for(dt)
        for _ in range(count):
            self._substep(dt / count)
        self.steps += 1
        return count

    def _substep(self, h: float) -> None:
        """One substep in phases over ranges of agents, with a barrier between two: think (timers,
        transitions, steering, motion; coasting under the budget), push (separation: each agent's push
        from its range's neighbour list, read from everyone's positions), apply (the pushes and the
        world's bounds) and finish (heading and phase; without the budget, apply is part of it). Each
        phase runs the same arithmetic on each agent whichever process steps it, so any number of
        workers gives the same crowd, bit for bit (``tests/test_agent_pool.py``)."""
        self.time += h
        if not self.n:
            return
        ranges = self._ready_ranges()
        self._update_flow()
        p = self._params
        p[P_H], p[P_TIME], p[P_SUBSTEPS], p[P_STEPS] = h, self.time, self.substeps, self.steps
        p[P_PLAYER:P_PLAYER + 2] = self.player
        if len(self.focus) > MAX_FOCUS:
            raise AIError(f"AI focus has {len(self.focus)} points; at most {MAX_FOCUS}")
        p[P_FOCUS_COUNT] = len(self.focus)
        for f, point in enumerate(self.focus):
            p[P_FOCUS + 2 * f:P_FOCUS + 2 * f + 2] = point
        if self.budgeted():
            k, b = self.config.think_every, self.substeps % self.config.think_every
            p[P_BLOCK], p[P_BLOCK + 1] = b * self.n // k, (b + 1) * self.n // k
        else:
            p[P_BLOCK] = p[P_BLOCK + 1] = -1.0
        p[P_HAVE_PAIRS] = bool(self._pairs)
        answers = self._phase(THINK, ranges)
        self.player_hits_taken += int(answers[1:, 0].sum())  # this process's range counted its own
        if answers[:, 1].any():
            self._pairs = False
        started = time.perf_counter()
        p[P_REBUILD] = self._prepare_lists(float(answers[:, 2].max()))
        if ranges > 1:
            self._sync_workers()  # a grid that outgrew its block is in a new one
        p[P_GAIN] = min(self.config.separation_stiffness * h, 1.0)
        self._phase(PUSH, ranges)
        self.separation_seconds += time.perf_counter() - started
        if p[P_BLOCK] >= 0:  # the budget's thinkers are not cut by range: the pushes land first, everywhere
            self._phase(APPLY, ranges)
        self._phase(FINISH, ranges)
        self.substeps += 1
