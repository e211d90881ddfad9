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

Stability: dt is clamped to ``max_dt`` and stepped in equal substeps of at most ``substep``.
Separation is a position correction, not a force: each substep removes at most the fraction
min(stiffness x h, 1) of each overlap and moves an agent at most half the separation radius, so a
stiffness x dt far above 1 stays bounded. Neighbours come from a uniform grid over the world (agents
sorted by cell), never from all pairs, and the pair list is reused across substeps until an agent has
moved far enough to invalidate it. Positions are float64; the renderer subtracts the
camera before anything becomes float32.

Think budget (settings think_every, think_radius, think_from): in a big crowd, zombies far from the
player and the camera (``focus``) that wander or lie dead think every think_every substeps, a block
of consecutive agents at a time, and coast at their velocity and phase rate in between; everyone
else, and every action, is stepped exactly as without it (``_budgeted_think``).

Several cores (setting workers; crowd.sim.agent_pool): a crowd of 2 x MIN_RANGE agents or more is cut
into ranges of consecutive agents, one per process, its arrays in shared memory; each substep is a few
phases with a barrier between them (``_substep``). Random draws are keyed by agent and substep and
each range builds its own neighbour list from one shared grid, so any number of workers gives the
same crowd, bit for bit. Arrays are changed in place, never rebound, so the workers see every change
the main process makes between steps (``hit``, the tests' placements).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np

from ..asset.model import CONTACT_M, foot_joints
from ..asset.pose import global_matrices, sample_clip
from ..frame import CLIP, MASK, MAX_LAYERS, PHASE, WEIGHT, FrameError, Instances, cast_counts, cast_firsts, cast_moves, empty_layers
from ..search import golden_section_max
from ..settings import SETTINGS, group
from ..spans import over_spans
from .agent_pool import PARAMS, AgentPool, PoolError, SharedArrays, available_cores

LAYERS = MAX_LAYERS
# States (int8).
WANDER, CHASE, ATTACK, HIT, DYING, DEAD = range(6)
STATE_NAMES = ("wander", "chase", "attack", "hit", "dying", "dead")
# Actions (int8): which clip layer 3 plays.
NO_ACTION, ACT_ATTACK, ACT_HIT, ACT_DEATH = range(4)
ACTION_ROLES = (None, "attack", "hit", "death")
LAYER_RUN = 16_384  # agents whose layers write_layers fills at a time (1 MB: they stay in the cache)
MAX_ACTION_WEIGHT = 1000.0  # an upper-body action at full fade: 99.9 % of the upper body
MIN_RANGE = 1_024  # agents a process steps at least: a smaller share saves less than waking a worker costs
SEPARATION_CELL_CAP = 48  # neighbours considered per row of three cells (bounds the work when many agents pile up)
TINTS = np.array([[150, 170, 130], [170, 150, 130], [130, 150, 160], [180, 180, 160], [140, 160, 120], [160, 130, 140]], np.uint8)
# Phases of a substep (run on every range of agents, a barrier between two) and their numbers' places.
THINK, PUSH, APPLY, FINISH, WRITE_LAYERS, HEADINGS = 1, 2, 3, 4, 5, 6
P_H, P_TIME, P_SUBSTEPS, P_STEPS, P_PLAYER, P_RANGES, P_N, P_BLOCK, P_GAIN, P_HAVE_PAIRS, P_REBUILD, P_SIDE = (
    1, 2, 3, 4, 5, 7, 8, 9, 11, 12, 13, 14)
P_FOCUS_COUNT, P_FOCUS = 15, 16
MAX_FOCUS = (PARAMS - P_FOCUS) // 2
_RESPAWN, _WANDER = 1, 2  # what a keyed draw is for (see CrowdAI._draws)
_MASK64 = (1 << 64) - 1
DEFAULT_WALK_SPEED = 1.0  # m/s, for imported walks without a stride (their feet will slide)
DEFAULT_RUN_SPEED = 3.0
RUN_OVER_WALK = 1.8  # top speed of a runner over a walker when one clip plays both
FOOT_SAMPLES = 64  # phases a locomotion clip's pivot is tabled at (Motion.pivots)
WALK_SLOWEST = 0.25  # the slowest a walk plays, as a share of its own rate (Motion.walk_slowest)
# Obstacles (a town: crowd.asset.town.Obstacles). An agent's centre is kept CLEARANCE metres from every
# obstacle, by its signed distance field; chasers find their way around buildings by a flow field of
# FLOW_CELLS x FLOW_CELLS cells of FLOW_CELL metres around the player, made anew when the player
# crosses a cell.
CLEARANCE = 0.35
FLOW_CELL = 1.0
FLOW_CELLS = 96
FLOW_BLOCKED = CLEARANCE + 0.05  # a flow cell whose centre is nearer an obstacle than this is a wall (a 2 m alley stays open)
FLOW_DIRECT = 3.0  # metres from the player within which a chaser goes straight at it
_FLOW_ARRAYS = ("_flow_steps", "_flow_usable", "_flow_corner")
# A field takes 4.5 to 5 ms on the dev container (about 70 units of flow_field_work): made in one substep
# it made the AI's slowest substeps. The main process does FLOW_WORK units a substep, before the think,
# and publishes the field into the agents' shared arrays when it is done (about 6 substeps, 0.1 s, after
# the player crossed into the cell), so every process steps with the same field: the same crowd for any
# worker count, and any machine.
FLOW_WORK = 12


def _relaxations(open_: np.ndarray, target: tuple[int, int]):
    """Shortest 8-neighbour path lengths (in cells; diagonals sqrt 2) from every open cell of a grid to
    `target`, inf where walled off, as a generator: None after each relaxation pass, then the lengths. Every
    cell relaxed from its 8 neighbours at once, until nothing shortens (a pass per cell of the longest
    path: 54 to 67 passes, 4 to 5 ms for the town's 96 x 96 window on the dev container). Written here
    rather than taken from scipy (csgraph's Dijkstra): the AI is numpy only, this is the one graph
    search it needs, and passes can be spread over substeps (_update_flow). A version relaxing whole
    lines at once (running minimums along rows, columns and diagonals) needed 7 passes but took 4.3 ms:
    numpy's running minimum costs more per cell than the passes it saves."""
    n, m = open_.shape
    dist = np.full((n, m), np.inf)
    dist[target] = 0.0
    steps = [(di, dj, math.hypot(di, dj)) for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj]
    for _ in range(4 * max(n, m)):
        before = dist.copy()
        for di, dj, w in steps:
            a = dist[max(di, 0):n + min(di, 0), max(dj, 0):m + min(dj, 0)]
            b = before[max(-di, 0):n + min(-di, 0), max(-dj, 0):m + min(-dj, 0)]
            np.minimum(a, b + w, out=a)
        dist[~open_] = np.inf
        dist[target] = 0.0
        if np.array_equal(dist, before):
            break
        yield None
    yield dist


def flow_field(obstacles, cell: tuple[int, int]) -> tuple:
    """The flow field toward the player's `cell` (see flow_field_work), made at once."""
    work = flow_field_work(obstacles, cell)
    while True:
        field = next(work)
        if field is not None:
            return field


def flow_field_work(obstacles, cell: tuple[int, int]):
    """The flow field toward the player's `cell`, as a generator of units of work of 0.05 to 0.3 ms (None),
    the last of which gives the field: (the window's first cell's corner (x, z), each cell's way down the
    path distances: di and dj (int8), and whether there is one), over FLOW_CELLS x FLOW_CELLS cells of
    FLOW_CELL metres centred on it (a cell whose centre is within FLOW_BLOCKED of an obstacle is a wall).
    The units are fixed by the field alone, not by time, so a field spread over substeps comes in at the
    same substep on any machine."""
    cell = np.asarray(cell, np.int64)
    corner = (cell - FLOW_CELLS // 2) * FLOW_CELL
    centres = corner[:, None] + (np.arange(FLOW_CELLS) + 0.5) * FLOW_CELL
    cx, cz = np.meshgrid(centres[0], centres[1], indexing="ij")
    open_ = obstacles.distance(cx, cz) >= FLOW_BLOCKED
    yield None
    passes = _relaxations(open_, (FLOW_CELLS // 2, FLOW_CELLS // 2))
    while (dist := next(passes)) is None:
        yield None
    dist *= FLOW_CELL
    downhill = _downhill(dist)
    while (steps := next(downhill)) is None:
        yield None
    step_i, step_j, usable = steps
    yield corner.astype(np.float64), step_i.astype(np.int8), step_j.astype(np.int8), usable


def _downhill(dist: np.ndarray):
    """Each cell's way down the distances: the neighbour (di, dj) nearest the target by path, and whether
    it is nearer than the cell itself (walls are inf). A cell the field calls a wall (an agent pressed
    against one stands in one) looks two cells out. Per cell, once per field: the chasers look it up.
    A generator: None after each row of 5 neighbours, then (di, dj, whether)."""
    n = dist.shape[0]
    padded = np.full((n + 4, n + 4), np.inf)
    padded[2:-2, 2:-2] = dist
    reach = np.where(np.isfinite(dist), 1, 2)
    best = np.full(dist.shape, np.inf)
    step_i, step_j = np.zeros(dist.shape, np.int64), np.zeros(dist.shape, np.int64)
    for di in range(-2, 3):
        for dj in range(-2, 3):
            if di or dj:
                d = np.where(max(abs(di), abs(dj)) <= reach, padded[2 + di:n + 2 + di, 2 + dj:n + 2 + dj], np.inf)
                better = d < best
                best = np.where(better, d, best)
                step_i, step_j = np.where(better, di, step_i), np.where(better, dj, step_j)
        yield None
    yield step_i, step_j, np.isfinite(best) & (best < dist)


class AIError(ValueError):
    """Bad AI input; the message is one line."""


_AI = {name: setting.default for name, setting in group("ai").items()}


@dataclass(frozen=True)
class AIConfig:
    """The AI's settings. Each one's default, bounds and help are declared once, in the ``ai`` group of
    crowd.settings; a test checks that these fields are that group."""

    substep: float = _AI['substep']
    max_dt: float = _AI['max_dt']
    notice_radius: float = _AI['notice_radius']
    forget_radius: float = _AI['forget_radius']
    reaction_min: float = _AI['reaction_min']
    reaction_max: float = _AI['reaction_max']
    attack_reach: float = _AI['attack_reach']
    attack_cooldown: float = _AI['attack_cooldown']
    separation_radius: float = _AI['separation_radius']
    separation_stiffness: float = _AI['separation_stiffness']
    max_accel: float = _AI['max_accel']
    turn_rate: float = _AI['turn_rate']
    plant_feet: bool = _AI['plant_feet']
    arrive_distance: float = _AI['arrive_distance']
    wander_radius: float = _AI['wander_radius']
    wander_speed: float = _AI['wander_speed']
    speed_min: float = _AI['speed_min']
    speed_max: float = _AI['speed_max']
    runner_share: float = _AI['runner_share']
    armed_share: float = _AI['armed_share']
    crossfade: float = _AI['crossfade']
    corpse_time: float = _AI['corpse_time']
    health: int = _AI['health']
    area_per_agent: float = _AI['area_per_agent']
    min_half_extent: float = _AI['min_half_extent']
    half_extent: float = _AI['half_extent']
    think_every: int = _AI['think_every']
    think_radius: float = _AI['think_radius']
    think_from: int = _AI['think_from']
    workers: int = _AI['workers']

    def validate(self) -> "AIConfig":
        for name, setting in group("ai").items():
            setting.check(getattr(self, name), AIError)
        # Relations between settings (each one's own bounds are the schema's).
        if self.reaction_max < self.reaction_min or self.speed_max < self.speed_min:
            raise AIError("AI ranges need min <= max (reaction, speed)")
        if self.forget_radius < self.notice_radius:
            raise AIError("AI forget_radius must be >= notice_radius")
        if self.substep > self.max_dt:
            raise AIError("AI needs substep <= max_dt")
        if self.think_every > 1 and self.think_radius < self.notice_radius:  # the budget may be used at some crowd size
            raise AIError("AI think_radius must be >= notice_radius (a zombie that may notice the player thinks every substep)")
        return self

    def half_extent_for(self, agents: int, free_share: float = 1.0) -> float:
        """The world's half width for a crowd: area_per_agent of open ground each, on a ground of which
        `free_share` is open (the rest buildings and cars)."""
        if self.half_extent > 0:
            return float(self.half_extent)
        return max(self.min_half_extent, 0.5 * math.sqrt(agents * self.area_per_agent / free_share))


@dataclass(frozen=True)
class Motion:
    """What the AI needs to know of the baked clips: indices, durations and locomotion strides."""

    clip: dict  # role → clip index in the bake, or -1 when the role has no clip
    duration: dict  # role → seconds (0 for roles without a clip)
    walk_stride: float  # metres per cycle
    run_stride: float
    walk_speed: float  # m/s at which the clip's feet do not slide (for a factor-1 agent)
    run_speed: float
    upper_body_mask: int  # mask row for upper-body actions, or -1 (whole body)
    head_count: int = 0
    weapon_count: int = 0
    notes: tuple = ()
    # Share of the walk speed down to which the walk plays alone, slowed (locomotion_weights): where its
    # slowed rate is idle's own, so the phase's rate does not jump as idle fades in; within [1/4, 1].
    walk_slowest: float = 1.0
    # Where agents pivot when they turn (turn_about_planted_foot): per clip (idle, walk, run) and phase
    # (FOOT_SAMPLES + 1 evenly spaced, the last at phase 1), the model-space (x, z) of the middle of the
    # foot joints on the ground and 1 where one is (3, FOOT_SAMPLES + 1, 3); None: about their origin.
    pivots: np.ndarray | None = dataclasses.field(default=None, compare=False)
    weapon_first: int = 0  # its first weapon's number among the cast's (a crowd of several characters)

    @staticmethod
    def from_bake(bake, roles: dict, strides: dict, upper_body_mask: int = -1, head_count: int = 0, weapon_count: int = 0,
                  clip_speed: dict | None = None) -> "Motion":
        """`clip_speed` (clip name → time scale, default 1) plays a clip faster or slower: its duration is
        divided by the scale, so a walk played 1.5x faster also moves 1.5x faster and its feet stay put."""
        clip, duration, notes = {}, {}, []
        for role in ("idle", "walk", "run", "attack", "hit", "death"):
            name = roles.get(role)
            clip[role] = bake.clip_index(name) if name else -1
            speed = SETTINGS["clip_speed"].check((clip_speed or {}).get(name, 1.0), AIError, f"clip {name!r}") if name else 1.0
            duration[role] = max(bake.clips[clip[role]].duration / speed, 1e-3) if name else 0.0
        walk_stride = float(strides.get(roles["walk"]) or 0.0)
        if walk_stride <= 0:
            walk_stride = DEFAULT_WALK_SPEED * duration["walk"]
            notes.append(f"walk clip {roles['walk']!r} has no stride; it moves at {DEFAULT_WALK_SPEED} m/s and its feet may slide")
        walk_speed = walk_stride / duration["walk"]
        if roles["run"] == roles["walk"]:
            # One clip for both: running is the walk played faster (the stride stays, the rate goes up).
            run_stride, run_speed = walk_stride, walk_speed * RUN_OVER_WALK
        else:
            run_stride = float(strides.get(roles["run"]) or 0.0)
            if run_stride <= 0:
                run_stride = DEFAULT_RUN_SPEED * duration["run"]
                notes.append(f"run clip {roles['run']!r} has no stride; it moves at {DEFAULT_RUN_SPEED} m/s and its feet may slide")
            run_speed = max(run_stride / duration["run"], walk_speed * 1.01)
        slowest = duration["walk"] / duration["idle"] if duration["idle"] > 0 else WALK_SLOWEST
        return Motion(clip, duration, walk_stride, run_stride, walk_speed, run_speed, int(upper_body_mask), int(head_count),
                      int(weapon_count), tuple(notes), float(np.clip(slowest, WALK_SLOWEST, 1.0)))


def upper_body_mask(skeleton) -> np.ndarray | None:
    """(1, J) mask: 1 for the first joint named like a spine and everything below it, else 0.
    None when no joint is named like a spine (then actions play on the whole body)."""
    names = [n.lower() for n in skeleton.names]
    start = next((j for j, n in enumerate(names) if any(w in n for w in ("spine", "chest", "torso"))), None)
    if start is None:
        return None
    mask = np.zeros(skeleton.joint_count, np.float32)
    mask[start] = 1.0
    for j, p in enumerate(skeleton.parents):  # parents come first, so one pass suffices
        if p >= 0 and mask[p] > 0:
            mask[j] = 1.0
    return mask[None]


def motion_for(character, bake, roles: dict, clip_speed: dict | None = None) -> Motion:
    """The Motion of a character's baked roles. Upper-body actions use mask row 0 when the skeleton has
    an upper body (the processor gets `upper_body_mask(skeleton)` as its masks); heads are the pieces of
    the "head" variation group; weapons are the props the character can hold in a socket."""
    strides = {c.name: (c.stride or 0.0) for c in character.clips}
    measured = []
    for role in ("walk", "run"):
        name = roles.get(role)
        if name and strides.get(name, 0.0) <= 0.0:  # (a walk that is also the run has its stride by now)
            stride = stride_from_feet(character, character.clip(name))
            if stride is not None:
                strides[name] = stride
                measured.append(name)
    mask_row = 0 if upper_body_mask(character.skeleton) is not None else -1
    heads = len({m.piece for m in character.meshes if m.group == "head"})
    weapons = len(character.props) if character.armed else 0
    motion = Motion.from_bake(bake, roles, strides, mask_row, heads, weapons, clip_speed)
    notes = motion.notes + tuple(f"clip {name!r} has no stride; measured from its planted feet: {strides[name]:.3f} m a cycle"
                                 for name in measured)
    return dataclasses.replace(motion, pivots=pivot_table(character, roles), notes=notes)


def _feet_over_cycle(character, clip, samples: int) -> tuple[np.ndarray, np.ndarray] | None:
    """A clip's foot joints at samples + 1 evenly spaced phases from 0 to 1 (float64 forward kinematics):
    their model-space positions (samples + 1, K, 3) and whether each is on the ground, within the contact
    height of its own lowest point; None for a skeleton without joints named like feet."""
    skeleton = character.skeleton
    feet = foot_joints(skeleton)
    if not feet:
        return None
    g = global_matrices(skeleton, sample_clip(skeleton, clip, np.linspace(0.0, 1.0, samples + 1)))
    pos = g[:, feet][..., :3, 3]
    return pos, pos[..., 1] - pos[..., 1].min(axis=0) <= CONTACT_M


def stride_from_feet(character, clip, samples: int = 240) -> float | None:
    """Metres a cycle the body of an in-place locomotion clip covers, measured from its feet: while a
    foot joint is within the contact height of its lowest point, it carries weight, and the body should
    move forward (+Z, the character's front) as fast as that foot moves back. The stride is the one that
    leaves the least slide in world space per metre walked, summed over every foot joint and contact
    step: the foot-skate measure itself (crowd.anim.foot_skate). None when the skeleton has no joint
    named like a foot or its feet are never on the ground. Clips that travel (root motion) have their
    stride from crowd.asset.root_motion instead."""
    cycle = _feet_over_cycle(character, clip, samples)
    if cycle is None:
        return None
    pos, down = cycle
    both = down[1:] & down[:-1]
    if np.count_nonzero(both) < max(8, samples // 20):
        return None
    step = np.diff(pos, axis=0)[both]  # (steps, 3) model-space moves of feet on the ground
    dx, dz = step[:, 0], step[:, 2]

    def slide(stride):  # metres slid in world space per metre walked, walking `stride` metres a cycle
        return np.hypot(dx, dz + stride / samples).sum() / stride

    # Over the strides the feet's own backward moves span, the slide per metre falls as the stride nears
    # the stance feet's speed and rises past it.
    stride, least = golden_section_max(lambda x: -slide(x), 1e-3, max(float(-dz.min()) * samples, 2e-3), 60)
    return stride if np.isfinite(least) else None


def pivot_table(character, roles: dict) -> np.ndarray | None:
    """Motion.pivots from the character's own clips (float64 forward kinematics), or None for a
    skeleton without joints named like feet."""
    if not foot_joints(character.skeleton):
        return None
    table = np.zeros((3, FOOT_SAMPLES + 1, 3))
    for r, role in enumerate(("idle", "walk", "run")):
        if roles.get(role):
            pos, down = _feet_over_cycle(character, character.clip(roles[role]), FOOT_SAMPLES)
            count = down.sum(axis=1)
            share = down / np.maximum(count, 1)[:, None]
            table[r, :, 0] = (share * pos[..., 0]).sum(axis=1)
            table[r, :, 1] = (share * pos[..., 2]).sum(axis=1)
            table[r, :, 2] = count > 0
    return table


def turn_about_planted_foot(m: Motion, phase, weights, hx0, hz0, hx1, hz1, scale) -> tuple[np.ndarray, np.ndarray]:
    """The ground shift (dx, dz) that turns agents from heading (hx0, hz0) to (hx1, hz1) about the foot
    they stand on instead of about their origin, as a walker pivots on its stance foot: that foot stays
    where it is in world space. Each locomotion clip's pivot at a phase is the middle of its foot joints
    within the contact height (above each one's own lowest point): one foot's heel and toe, or both
    feet's (Motion.pivots); the agent's is the mean of its clips' pivots, weighted by their layer weights
    (`weights`: idle, walk, run) among the clips with a foot down, if those weigh half or more; else (a
    run's flight) no shift. A planted foot still turns with the body (a foot lock would twist the leg
    instead), so its joints slide by their distance from the pivot times the turn."""
    n = np.shape(phase)[0]
    if m.pivots is None or n == 0:
        return np.zeros(n), np.zeros(n)
    f = np.asarray(phase, np.float64) * FOOT_SAMPLES
    i = np.minimum(np.maximum(np.floor(f), 0), FOOT_SAMPLES - 1).astype(np.int64)
    u = f - i
    mx, mz, down = np.zeros(n), np.zeros(n), np.zeros(n)
    for r, w in enumerate(weights):
        if not np.any(w):
            continue  # a clip nobody here plays (idle for walkers, run for most): no gathers
        a, b = m.pivots[r, i], m.pivots[r, i + 1]
        on = w * np.minimum(a[:, 2], b[:, 2])  # a clip whose foot lifts between the two samples does not count
        mx += on * (a[:, 0] + u * (b[:, 0] - a[:, 0]))
        mz += on * (a[:, 1] + u * (b[:, 1] - a[:, 1]))
        down += on
    planted = down >= 0.5
    inv = scale / np.maximum(down, 1e-12)
    mx, mz = mx * inv, mz * inv
    # Model (x, z) to world for a heading (hx, hz), the front: (hz x + hx z, -hx x + hz z).
    dx = (hz0 - hz1) * mx + (hx0 - hx1) * mz
    dz = (hx1 - hx0) * mx + (hz0 - hz1) * mz
    return np.where(planted, dx, 0.0), np.where(planted, dz, 0.0)


@dataclass
class _AgentMotion:
    """The Motion fields the locomotion functions read, per agent (arrays), for a crowd of several
    characters: locomotion_weights, blended_stride and phase_rate take it where they take a Motion."""

    walk_stride: np.ndarray
    run_stride: np.ndarray
    run_speed: np.ndarray
    walk_slowest: np.ndarray
    duration: dict  # {"idle": per agent}


_KIND_FIELDS = ("_m_walk_stride", "_m_run_stride", "_m_run_speed", "_m_walk_slowest", "_m_idle")  # per agent, a cast of several only


class PlayerScript:
    """The headless player: walks a circle through the crowd and strikes the nearest zombie in reach at
    a steady rhythm. Deterministic: it depends on time only."""

    def __init__(self, radius: float, speed: float = 1.6, strike_every: float = 0.9, strike_reach: float = 2.0):
        self.radius = float(radius)
        self.speed = float(speed)
        self.strike_every = float(strike_every)
        self.strike_reach = float(strike_reach)
        self._next_strike = self.strike_every

    def update(self, ai: "CrowdAI", survivor=None) -> None:
        """Move the player along its circle and strike on the beat: the AI's player point itself, or,
        with a `survivor` (crowd.sim.player), that character, told to run to the circle's point and to
        swing (its blow lands when the swing does)."""
        t = ai.time
        angle = t * self.speed / max(self.radius, 1e-3)
        point = ai.origin + self.radius * np.array([math.cos(angle), math.sin(angle)])
        if survivor is not None:
            survivor.walk_to(point)
        else:
            ai.player = point
        while t >= self._next_strike:
            self._next_strike += self.strike_every
            if survivor is not None:
                survivor.strike()
                continue
            target = ai.nearest_alive(ai.player, self.strike_reach)
            if target >= 0:
                ai.hit(np.array([target]))


class _Agents:
    """Some of the crowd's per-agent arrays under the AI's own names, for one think: views for a slice
    (a process's range, its part of a think block), gathered copies for an index array (the exact
    agents). ``commit()`` writes back the copies, and every array the think rebound (np.where makes new
    ones). ``ids(local)``: the crowd's numbers of its agents, for the keyed random draws."""

    def __init__(self, ai: "CrowdAI", selection):
        self._ai, self._selection = ai, selection
        self.ids = (lambda local: selection.start + local) if isinstance(selection, slice) else (lambda local: selection[local])
        self._was = {}
        for name in ai._names():
            self._was[name] = getattr(ai, name)[selection]
            setattr(self, name, self._was[name])

    def commit(self) -> None:
        gathered = not isinstance(self._selection, slice)
        for name, was in self._was.items():
            now = getattr(self, name)
            if now is was and not gathered:
                continue  # changed in place, through the view
            getattr(self._ai, name)[self._selection] = now


class CrowdAI:
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
        self.rng = np.random.default_rng(self.seed)
        origin = np.asarray(origin, np.float64)
        if origin.shape != (2,) or not np.all(np.isfinite(origin)):
            raise AIError("AI origin must be a finite (x, z) pair")
        self.origin = origin  # float64 centre of the world square
        self.time = 0.0
        self.player = origin.copy()
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

    @staticmethod
    def ids(local: np.ndarray) -> np.ndarray:
        """The crowd's own agent numbers (an ``_Agents`` maps its local ones)."""
        return local

    def _draws(self, ids: np.ndarray, purpose: int, count: int) -> np.ndarray:
        """(count, len(ids)) uniform numbers in [0, 1) for agents `ids`, keyed by (seed, agent, substep,
        purpose): the same for an agent whichever process steps it and whatever others draw, which a
        sequential generator cannot give. A counter-based generator: splitmix64's finaliser over the key
        (written here: numpy's Philox draws streams, not one number per key for many keys at once)."""
        base = (self.seed * 0x9E3779B97F4A7C15 + self.substeps * 0xD1B54A32D192ED03 + purpose * 0xAEF17502108EF2D9) & _MASK64
        key = np.asarray(ids).astype(np.uint64) * np.uint64(0xBF58476D1CE4E5B9) ^ np.uint64(base)
        out = np.empty((count, key.size))
        for row in range(count):
            z = key + np.uint64(((row + 1) * 0x9E3779B97F4A7C15) & _MASK64)
            z ^= z >> np.uint64(30)
            z *= np.uint64(0xBF58476D1CE4E5B9)
            z ^= z >> np.uint64(27)
            z *= np.uint64(0x94D049BB133111EB)
            z ^= z >> np.uint64(31)
            out[row] = (z >> np.uint64(11)) * (1.0 / (1 << 53))
        return out

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

    def _spawn(self, a, idx: np.ndarray, anywhere: bool) -> None:
        """New agents `idx` of `a` (the crowd itself, or the agents of one think): anywhere in the world
        (start, resize) or on its edges (respawn). Traits are drawn at first spawn only, so a respawned
        agent keeps its look, speed and weapon."""
        k = len(idx)
        if not k:
            return
        self._respawns += k  # an agent that comes back to life is in no pair of the neighbour list: the step rebuilds it
        a.spawned_step[idx] = self.steps
        cfg, rng, h = self.config, self.rng, self.half_extent
        if anywhere:
            pos = rng.uniform(-h, h, (k, 2))
            if self.obstacles is not None:  # on the streets: places in or by an obstacle are drawn again
                for _ in range(32):
                    blocked = np.flatnonzero(self.obstacles.distance(self.origin[0] + pos[:, 0], self.origin[1] + pos[:, 1]) < CLEARANCE + 0.1)
                    if not blocked.size:
                        break
                    pos[blocked] = rng.uniform(-h, h, (blocked.size, 2))
            yaw = rng.uniform(-math.pi, math.pi, k)
            a.phase[idx] = rng.uniform(0.0, 1.0, k)
            a.speed_factor[idx] = rng.uniform(cfg.speed_min, cfg.speed_max, k)
            a.reaction[idx] = rng.uniform(cfg.reaction_min, cfg.reaction_max, k)
            a.runner[idx] = rng.uniform(0, 1, k) < cfg.runner_share
            a.scale[idx] = rng.uniform(0.92, 1.08, k)
            a.tint[idx, :3] = TINTS[rng.integers(0, len(TINTS), k)]
            a.tint[idx, 3] = 255
            # Each agent's traits from its own character: its head choices, weapons and speeds.
            kind = a.kind[idx] if len(self.motions) > 1 else 0
            heads = np.array([max(m.head_count, 1) for m in self.motions])[kind]
            weapons = np.array([m.weapon_count for m in self.motions])[kind]
            a.head[idx] = rng.integers(0, heads, k)
            armed = (rng.uniform(0, 1, k) < cfg.armed_share) & (weapons > 0)
            a.weapon[idx] = np.where(armed, np.array([m.weapon_first for m in self.motions])[kind] + rng.integers(0, np.maximum(weapons, 1), k), -1)
            a.walk_top[idx] = self._walk_speed[kind] * a.speed_factor[idx]
            a.chase_top[idx] = np.where(a.runner[idx], self._run_speed[kind], self._walk_speed[kind]) * a.speed_factor[idx]
        else:  # while stepping: draws keyed by agent and substep, so any split of the crowd gives the same ones
            draw = self._draws(a.ids(idx), _RESPAWN, 3)
            side = np.minimum((draw[0] * 4.0).astype(np.int64), 3)
            along = -h + 2.0 * h * draw[1]
            edge = np.where(side % 2 == 0, -1.0, 1.0) * (h - 0.5)
            pos = np.where((side < 2)[:, None], np.stack([edge, along], axis=1), np.stack([along, edge], axis=1))
            yaw = np.arctan2(-pos[:, 0], -pos[:, 1])  # face the middle
        a.x[idx] = self.origin[0] + pos[:, 0]
        a.z[idx] = self.origin[1] + pos[:, 1]
        if self.obstacles is not None:  # (an edge of the world that runs through a building)
            a.x[idx], a.z[idx] = self.keep_out(a.x[idx], a.z[idx])
        a.hx[idx], a.hz[idx] = np.sin(yaw), np.cos(yaw)
        a.vx[idx] = a.vz[idx] = 0.0
        a.tx[idx], a.tz[idx] = a.x[idx], a.z[idx]
        a.state[idx] = WANDER
        a.state_time[idx] = 0.0
        a.aware[idx] = 0.0
        a.pause[idx] = rng.uniform(0.0, 2.0, k) if anywhere else 2.0 * draw[2]
        a.health[idx] = int(cfg.health)
        a.action[idx] = NO_ACTION
        a.action_time[idx] = 0.0
        a.cooldown[idx] = 0.0

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
        count = max(1, math.ceil(dt / self.config.substep - 1e-9)) if dt > 0.0 else 0
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

    def _phase(self, code: int, ranges: int) -> np.ndarray:
        """Phase `code` on every range: range 0 here, ranges 1.. in the workers. Returns each range's
        answer, (ranges, 3)."""
        p = self._params
        p[0], p[P_RANGES], p[P_N] = code, ranges, self.n
        if ranges == 1:
            return np.array([self.run_phase(code, p, -1)], np.float64)
        mine = []
        theirs = self._on_pool(self._pool.run, code, ranges - 1, lambda: mine.append(self.run_phase(code, p, -1)))
        return np.concatenate([np.array([mine[0]], np.float64), theirs[:, :3]])

    def _workers(self) -> int:
        """Processes that may step the crowd, this one included (the ``workers`` setting; 0: one per core)."""
        return self.config.workers or min(available_cores(), 64)

    def _ready_ranges(self) -> int:
        """How many ranges this substep's crowd is cut into (at least MIN_RANGE agents each), with the
        worker pool started, stopped or told of new arrays and settings as that needs."""
        ranges = self.ranges()
        if self._pool is not None and self._pool.closed:  # it failed or was interrupted: a new one is started
            self._stop_pool(copy=False)
        if ranges > 1 and self._pool is None:
            self._start_pool(self._workers() - 1)
        if ranges > 1:
            self._sync_workers()
        return ranges

    def _sync_workers(self) -> None:
        """Tell the workers of new arrays or settings, if there are any since they last heard."""
        if self._stale:
            grid = self._grid_block
            message = dict(block=(self._block.name, self._block.layout), grid=(grid.name, grid.layout) if grid else None,
                           config=self.config, motions=self.motions, shares=self.shares, cast=self.cast, seed=self.seed,
                           origin=self.origin, half_extent=self.half_extent, n=self.n, obstacles=self.obstacles)
            self._on_pool(self._pool.sync, [message] * self._pool.workers)
            self._stale = False

    def _on_pool(self, call, *args):
        """`call(*args)` on the pool; a worker that failed or exited is the AI's one line, and the pool is
        dropped (the arrays stay where they are; the next substep starts a new pool)."""
        try:
            return call(*args)
        except PoolError as error:
            self._stop_pool(copy=False)
            raise AIError(str(error)) from None

    def _start_pool(self, workers: int) -> None:
        """Start the workers and move the agents' arrays (and the neighbour list) into shared memory."""
        try:
            self._pool = AgentPool(workers, CrowdAI.worker_side)
        except (OSError, PoolError) as error:
            raise AIError(f"AI workers could not start: {str(error).splitlines()[0]}") from None
        self._params = self._pool.params  # the phases' numbers, now read by the workers too
        self._rehome()

    def _stop_pool(self, copy: bool = True) -> None:
        """Stop the workers; the arrays go back to this process's memory (`copy`: with their state)."""
        pool, self._pool = self._pool, None
        if pool is not None:
            self._params = self._params.copy()
            pool.close()
        if copy:
            self._rehome()

    def _rehome(self) -> None:
        """The same arrays, values and neighbour list in the memory the pool's state asks for."""
        kept = {name: getattr(self, name) for name in self._layout(self.n)}
        was = self._allocate(self.n)  # (the neighbour lists are built anew: each range's is its process's own)
        for name, array in kept.items():
            getattr(self, name)[...] = array
        del kept
        if was is not None:
            was.close()

    def take_workers(self, other: "CrowdAI") -> None:
        """Step with `other`'s worker processes from now on (a new round's new crowd: starting 15 processes
        again froze the first frame of every round for 0.4 s on the dev container, 1 s on the H200 host).
        `other` is left without them (and is to be closed); nothing happens if it has none, if one of them
        has exited, or if they are another size."""
        pool = other._pool
        if pool is None or not pool.healthy or self._pool is not None or other.config.workers != self.config.workers:
            return  # (a pool that lost a worker is left to `other`, whose close() stops it; this crowd starts its own)
        other._pool, other._params = None, other._params.copy()  # `other` keeps its arrays: its close() frees them
        params = self._params
        self._pool, self._params = pool, pool.params
        try:
            self._rehome()  # this crowd's arrays into shared memory; the next substep tells the workers (_stale)
        except BaseException:
            self._pool, self._params = None, params
            pool.close()
            raise

    def close(self) -> None:
        """Stop the worker processes and free the shared memory (also done when the AI is collected)."""
        self._stop_pool(copy=True)
        if self._grid_block is not None:
            self._grid_block.close()
            self._grid_block = None

    @classmethod
    def worker_side(cls) -> "CrowdAI":
        """The AI in a worker process: arrays mapped from the main process's block by ``sync_worker``."""
        ai = cls.__new__(cls)
        ai._block = ai._grid_block = ai._pool = ai._range_list = None
        ai._respawns, ai.player_hits_taken, ai.focus, ai.rng = 0, 0, (), None  # (a worker spawns only at edges: keyed draws)
        ai.obstacles = None
        return ai

    def sync_worker(self, message: dict | None) -> None:
        """(A worker) map the arrays and take the settings the main process sent; None: unmap all."""
        for name in list(self.__dict__):
            if isinstance(self.__dict__[name], np.ndarray) and name not in ("origin", "player"):
                del self.__dict__[name]
        for block in (self._block, self._grid_block):
            if block is not None:
                block.close()
        self._block = self._grid_block = None
        if message is None:
            return
        self.config, self.motions, self.shares, self.seed = message["config"], message["motions"], message["shares"], message["seed"]
        if getattr(self, "obstacles", None) is None or message["obstacles"] is None or self.obstacles.boxes != message["obstacles"].boxes:
            self.obstacles = message["obstacles"]  # (its distance field is built here, on first use; the flow field is shared)
        self.origin, self.half_extent, self.n, self.cast = message["origin"], message["half_extent"], message["n"], message["cast"]
        self._kind_fields = _KIND_FIELDS if len(self.motions) > 1 else ()
        self._motion_tables()
        self._layer_template = {}
        self._block = SharedArrays(*reversed(message["block"]))
        for name, array in self._block.arrays.items():
            setattr(self, name, array)
        if message["grid"] is not None:
            self._grid_block = SharedArrays(*reversed(message["grid"]))
            self._cell_first = self._grid_block.arrays["first"]

    def run_phase(self, code: int, p: np.ndarray, index: int) -> tuple:
        """Phase `code` on this process's share of the agents (range index + 1 of p's count; the main
        process is index -1), with the substep's numbers `p`. Returns up to three numbers."""
        ranges, n, r = int(p[P_RANGES]), int(p[P_N]), index + 1
        lo, hi = r * n // ranges, (r + 1) * n // ranges
        if index >= 0:  # a worker: the substep's numbers, as the main process holds them
            self.time, self.substeps, self.steps = float(p[P_TIME]), int(p[P_SUBSTEPS]), int(p[P_STEPS])
            self.player = p[P_PLAYER:P_PLAYER + 2].copy()
            self.focus = tuple(p[P_FOCUS + 2 * f:P_FOCUS + 2 * f + 2].copy() for f in range(int(p[P_FOCUS_COUNT])))
        h = float(p[P_H])
        if code == THINK:
            block = None
            if p[P_BLOCK] >= 0:  # this process's share of the budget's block: a slice of it, not of its range
                b0, b1 = int(p[P_BLOCK]), int(p[P_BLOCK + 1])
                block = (b0, b1, slice(b0 + r * (b1 - b0) // ranges, b0 + (r + 1) * (b1 - b0) // ranges))
            return self._think_range(lo, hi, h, block, bool(p[P_HAVE_PAIRS]))
        if code == PUSH:
            if p[P_REBUILD]:
                self._build_list(lo, hi, int(p[P_SIDE]))
            self._range["push"] = self._push_range(lo, hi, float(p[P_GAIN]))
        elif code == APPLY:
            self._apply_range(lo, hi, self._range.pop("push"))
        elif code == FINISH:
            self._finish_range(lo, hi, h)
        elif code == WRITE_LAYERS:
            self._write_layer_range(self._layer_out, lo, hi)
        elif code == HEADINGS:
            np.arctan2(self.hx[lo:hi], self.hz[lo:hi], out=self._yaw_out[lo:hi], casting="same_kind")
        else:
            raise AIError(f"unknown AI phase {code}")
        return (0.0, 0.0, 0.0)

    def _think_range(self, lo: int, hi: int, h: float, block, have_pairs: bool) -> tuple:
        """The think phase of agents lo..hi, or under the budget (`block`: the block's bounds and this
        process's slice of it) of this process's share: (strikes on the player, respawns, the largest
        squared move since the neighbour lists' build among the agents it moved, 0 without lists)."""
        hits, self._respawns = self.player_hits_taken, 0
        if block is None:  # every agent thinks
            group = _Agents(self, slice(lo, hi))
            self._range = {"near": self._think_a(group, h, h)}
            group.commit()
            moved = [(slice(lo, hi), None)]
        else:
            self._range = self._budgeted_think(lo, hi, h, *block)
            # What this process moved: its range's coasting agents, its slice of the block, its exact agents.
            moved = [(slice(lo, hi), self._range["coasting"]), (self._range["block"], None), (self._range["exact"], None)]
        farthest = 0.0
        if have_pairs:
            for agents, mask in moved:
                mx, mz = self.x[agents] - self._pairs_x[agents], self.z[agents] - self._pairs_z[agents]
                moved2 = mx * mx + mz * mz if mask is None else np.where(mask, mx * mx + mz * mz, 0.0)
                if moved2.size:
                    farthest = max(farthest, float(np.max(moved2)))
        return (float(self.player_hits_taken - hits), float(self._respawns), farthest)

    def _apply_range(self, lo: int, hi: int, push) -> None:
        """Agents lo..hi: their separation pushes (``_push_range``'s), then the world's bounds."""
        if push is not None:
            agents, push_x, push_z = push
            self.x[agents] += push_x
            self.z[agents] += push_z
            if self.config.plant_feet:
                self._step_with_push(agents, push_x, push_z)
        self._bound(lo, hi)
        if self.obstacles is not None:
            self._clear_obstacles(lo, hi)

    def _step_with_push(self, agents: np.ndarray, push_x: np.ndarray, push_z: np.ndarray) -> None:
        """A push along a walking agent's heading moves its body as its own steps do, so its locomotion
        phase moves with it (backward for a push from the front): the planted foot stays where it stands.
        In a blend at walk-or-run weight w (1 - idle's), the stance foot moves w x the blended stride per
        cycle; below w = 1/2 the push is left a slide rather than spin the legs."""
        m = self._m(agents=agents)
        speed = np.sqrt(self.vx[agents] ** 2 + self.vz[agents] ** 2)
        w_idle, _, _, run_t = locomotion_weights(m, speed, self.walk_top[agents], self.speed_factor[agents])
        stepping = (w_idle <= 0.5) & (self.state[agents] < DYING)
        if not np.any(stepping):
            return
        stride = (1.0 - w_idle) * blended_stride(m, run_t, self.scale[agents])
        along = push_x * self.hx[agents] + push_z * self.hz[agents]
        phase = self.phase[agents]
        advance_phase(phase, np.where(stepping, along / np.maximum(stride, 1e-9), 0.0))
        self.phase[agents] = phase

    def _finish_range(self, lo: int, hi: int, h: float) -> None:
        """The finish phase: heading and phase of this process's agents (and, without the budget, their
        pushes and bounds first)."""
        state, self._range = self._range, None
        if "near" in state:
            self._apply_range(lo, hi, state["push"])
            group = _Agents(self, slice(lo, hi))
            self._think_b(group, h, h, h, *state["near"])
            group.commit()
            return
        exact, block = state["exact"], state["block"]
        group = _Agents(self, exact)
        self._think_b(group, h, h, h, *state["near_exact"])
        group.commit()  # (the copy holds the old flags: commit first, then say who stays exact)
        self._exact[exact] = self._must_be_exact(group)
        group = _Agents(self, block)
        self._think_b(group, state["think_h"], state["move_h"], h, *state["near_block"])
        self._exact[block] |= self._must_be_exact(group)  # from now on with the exact ones (their pending time is 0)
        group.commit()

    def ranges(self) -> int:
        """Processes that step the crowd now, this one included (1 below 2 x MIN_RANGE agents)."""
        return max(1, min(self._workers(), self.n // MIN_RANGE))

    def exact_count(self) -> int:
        """Zombies that think every substep: all of them without the budget."""
        return int(np.count_nonzero(self._exact)) if self.budgeted() else self.n

    def budgeted(self) -> bool:
        """Whether the think budget is in use: think_every above 1, for a crowd of think_from or more."""
        return self.config.think_every > 1 and self.n >= self.config.think_from

    def _budgeted_think(self, lo: int, hi: int, h: float, b0: int, b1: int, block: slice) -> dict:
        """The think budget's think phase (crowd.settings: think_every, think_radius): agents that must
        be exact (near the player or a focus point, or doing anything but wandering and lying dead)
        think every substep; the rest are cut into think_every blocks of consecutive agents, and one
        block (agents b0..b1) thinks per substep, over the time since it last did. Between thinks an
        agent keeps its velocity and phase rate: its position and phase move every substep (no
        stutter), it goes on turning toward the heading its think chose, and its timers, steering and
        animation weights catch up when it thinks. An exact agent is stepped exactly as with the budget
        off: it takes no time from the budget, and its substep is the same arithmetic.

        Who does what, so that the processes share the block's work evenly and never touch one agent
        at once: each thinks its slice `block` of the block (through views) and the block's exact
        agents in it, the exact agents of its range lo..hi outside the block (gathered and scattered
        back), and coasts the rest of its range. Returns what the finish phase needs."""
        in_block = self._exact[block]  # exact agents inside the block think with the exact ones, not here
        think_h = np.where(in_block, 0.0, self._pending[block] + h)  # time since the block's agents last thought
        move_h = np.where(in_block, 0.0, h)  # this substep's motion (the rest was moved between thinks)
        self._pending[block] = 0.0

        # The block's slice thinks through views, its exact agents too (with no time: they think below);
        # what its first half changes of them (a transition seen from where they stand after moving, a
        # timer) is put back, so they start their exact substep from where the last one left them.
        inside = block.start + np.flatnonzero(in_block)
        restore = _Agents(self, inside)
        group = _Agents(self, block)
        near_block = self._think_a(group, think_h, move_h)
        group.commit()
        restore.commit()
        thinking = self._exact[lo:hi].copy()  # the range's exact agents, and below its part of the block
        blocked = slice(min(max(b0, lo), hi) - lo, max(min(b1, hi), lo) - lo)
        outside = thinking.copy()
        outside[blocked] = False
        exact = np.concatenate([lo + np.flatnonzero(outside), inside])
        group = _Agents(self, exact)
        near_exact = self._think_a(group, h, h)
        group.commit()

        # The rest of the range moves on at its velocity and phase rate (and is separated with everyone).
        # Only those agents are written (`where=`): the range's part of the block and its exact agents
        # there belong to the processes thinking them, which write them at the same time.
        thinking[blocked] = True
        coasting = ~thinking
        for position, velocity in ((self.x[lo:hi], self.vx[lo:hi]), (self.z[lo:hi], self.vz[lo:hi])):
            np.add(position, velocity * h, out=position, where=coasting)
        advance_phase(self.phase[lo:hi], self.phase_rate[lo:hi] * h, where=coasting)
        pending = self._pending[lo:hi]
        np.add(pending, h, out=pending, where=coasting)
        turning = lo + np.flatnonzero(self._coast_turn[lo:hi] & coasting)
        if turning.size:
            self._coast_turns(turning, self.config.turn_rate * h)
        return dict(exact=exact, block=block, think_h=think_h, move_h=move_h, near_block=near_block, near_exact=near_exact,
                    coasting=coasting)

    def _must_be_exact(self, a) -> np.ndarray:
        """Agents of `a` that think every substep: all but the wandering and the dead, and everyone
        within think_radius of the player or of a focus point (the camera)."""
        r2 = self.config.think_radius ** 2
        exact = (a.state != WANDER) & (a.state != DEAD)
        for fx, fz in (self.player, *self.focus):
            dx, dz = a.x - float(fx), a.z - float(fz)
            exact |= dx * dx + dz * dz < r2
        return exact

    def _think_a(self, a, h, move):
        """The first half of a substep for the agents of `a` (the crowd itself, or an ``_Agents``):
        timers and transitions, steering and velocity over `h` seconds (a scalar, or per agent: the
        time since they last thought), and this substep's motion over `move`. Returns what the second
        half needs."""
        cfg = self.config
        px, pz = float(self.player[0]), float(self.player[1])
        to_px, to_pz = px - a.x, pz - a.z
        dist = np.sqrt(to_px * to_px + to_pz * to_pz)
        state = a.state
        a.state_time += h
        a.action_time += h
        a.cooldown -= h

        # Transitions; events are rare, so they work on index lists.
        done = np.flatnonzero(a.action_time >= self.action_length(a.action, self._kind_of(a)))
        if done.size:
            s = state[done]
            back = done[(s == ATTACK) | (s == HIT)]
            a.cooldown[back] = np.where(state[back] == ATTACK, cfg.attack_cooldown, 0.0)
            state[back] = CHASE
            a.action[back] = NO_ACTION
            died = done[s == DYING]
            state[died] = DEAD
            a.state_time[died] = 0.0
        respawn = np.flatnonzero((a.state_time >= cfg.corpse_time) & (state == DEAD))
        self._spawn(a, respawn, anywhere=False)
        near = dist < cfg.notice_radius
        a.aware += h
        a.aware[~near] = 0.0
        wandering = state == WANDER
        notice = np.flatnonzero(wandering & (a.aware >= a.reaction))
        state[notice] = CHASE
        lost = np.flatnonzero((dist > cfg.forget_radius) & (state == CHASE))
        state[lost] = WANDER
        if np.any(self._role_clip["attack"] >= 0):
            ready = (dist < cfg.attack_reach) & (a.cooldown <= 0.0) & (state == CHASE)
            if len(self.motions) > 1:
                ready &= self._role_clip["attack"][a.kind] >= 0  # characters without an attack clip do not strike
            strike = np.flatnonzero(ready & (h > 0.0) if np.ndim(h) else ready)  # agents given no time strike nobody
            self._start(strike, ATTACK, ACT_ATTACK, a)
            self.player_hits_taken += int(strike.size)

        # Desired velocity: wanderers walk slowly to their target, chasers to the player, the rest stand.
        chasing = state == CHASE
        wandering = state == WANDER
        if wandering.any():
            self._wander(a, wandering, h)
        dx = np.where(chasing, to_px, a.tx - a.x)
        dz = np.where(chasing, to_pz, a.tz - a.z)
        if self.obstacles is not None and chasing.any():  # around the buildings, by the flow field to the player
            c = np.flatnonzero(chasing)
            ux, uz = self._flow_directions(a.x[c], a.z[c], to_px[c], to_pz[c])
            dx[c], dz[c] = ux * dist[c], uz * dist[c]
        d = np.sqrt(dx * dx + dz * dz)
        top = np.where(chasing, a.chase_top, cfg.wander_speed * a.walk_top * (wandering & (a.pause <= 0.0)))
        gap = np.where(chasing, d - 0.8 * cfg.attack_reach, d)
        speed = top * np.minimum(np.maximum(gap * (1.0 / cfg.arrive_distance), 0.0), 1.0)
        scale = speed / np.maximum(d, 1e-9)
        # Velocity with limited acceleration; the dying and the dead stop at once (no sliding corpses).
        cx, cz = dx * scale - a.vx, dz * scale - a.vz
        limit = np.minimum(1.0, (cfg.max_accel * h) / np.maximum(np.sqrt(cx * cx + cz * cz), 1e-12))
        a.vx += cx * limit
        a.vz += cz * limit
        still = np.flatnonzero(state >= DYING)
        a.vx[still] = 0.0
        a.vz[still] = 0.0
        a.x += a.vx * move
        a.z += a.vz * move
        return to_px, to_pz, dist

    def _think_b(self, a, h, move, substep: float, to_px, to_pz, dist) -> None:
        """The second half, after separation: heading (turned by at most turn_rate x `substep`, this
        substep's length, however long since the agent last thought: a budgeted agent goes on turning
        toward the same goal between thinks, see _coast_turns) and the locomotion phase (advanced over
        `move`)."""
        cfg = self.config
        state = a.state
        # Heading: a unit vector turned toward the motion (or toward the player while attacking) by at
        # most turn_rate * h, rotating by a fixed angle instead of going through angles (no trig per agent).
        speed = np.sqrt(a.vx * a.vx + a.vz * a.vz)
        attacking = state == ATTACK
        gx = np.where(attacking, to_px, a.vx)
        gz = np.where(attacking, to_pz, a.vz)
        glen = np.where(attacking, dist, speed)
        turning = (glen > 0.05) & (state < DYING)
        budgeted = np.ndim(h) > 0
        if budgeted:
            turning &= h > 0.0  # agents that do not think here (exact ones inside a block) keep their heading
        hx0, hz0 = a.hx, a.hz
        m = self._m(a)
        weights = locomotion_weights(m, speed, a.walk_top, a.speed_factor)  # (idle, walk, run, run share)
        ux, uz = self._turn(a, turning, gx, gz, glen, cfg.turn_rate * substep)
        self._pivot(a, np.flatnonzero(turning & (a.action == NO_ACTION) & ((a.hx != hx0) | (a.hz != hz0))), hx0, hz0,
                    weights[:3])
        if budgeted:  # those not at their goal yet turn on toward it, a substep's worth at a time, until they think again
            np.copyto(a._goal_x, ux)
            np.copyto(a._goal_z, uz)
            np.copyto(a._coast_turn, turning & ((a.hx != ux) | (a.hz != uz)))

        # Locomotion phase: speed over the blended stride (idle plays at its own rate while standing),
        # for the share of the motion along the heading. A heading that lags the motion (it turns at
        # turn_rate) walks forward only that share; the planted feet keep pace with it, and the rest is a
        # sideways slide no forward clip can follow (crowd.anim.foot_skate measures it).
        run_t = weights[3]
        forward = np.minimum(np.maximum((a.vx * a.hx + a.vz * a.hz) / np.maximum(speed, 1e-12), 0.0), 1.0)
        rate = phase_rate(m, speed, a.walk_top, run_t, a.scale) * np.where(speed > 0.0, forward, 1.0)
        advance_phase(a.phase, rate * move)
        if self.budgeted():
            a.phase_rate[:] = rate  # what the phase advances by until the agent thinks again

    def _turn(self, a, turning: np.ndarray, gx, gz, glen, step: float):
        """Turn each heading toward (gx, gz) by at most `step` radians. Headings within `step` of their
        goal snap to it; only the few farther off are rotated, by a fixed angle (no trig per agent).
        Rotation keeps the length to within rounding, about 1e-16 per step: 1e-10 after ten hours.
        Returns the goal directions."""
        inv = 1.0 / (glen + 1e-30)
        ux, uz = gx * inv, gz * inv
        hx, hz = a.hx, a.hz
        near = hx * ux + hz * uz >= math.cos(step)
        snap = turning & near
        far = np.flatnonzero(turning & ~near)
        a.hx = np.where(snap, ux, hx)
        a.hz = np.where(snap, uz, hz)
        if far.size:
            a.hx[far], a.hz[far] = _rotate_toward(hx[far], hz[far], ux[far], uz[far], step)
        return ux, uz

    def _coast_turns(self, coasting: np.ndarray, step: float) -> None:
        """Between thinks: the budgeted agents still turning (`coasting`, indices) turn toward the goal
        their last think set, by `step` as an exact agent turns each substep, snapping when within it.
        They turn about their origin: a coasting agent is far from the player and the camera, where a
        foot's pivot is not seen, and pivoting them cost 1 ms a step at 100,000 agents on one core."""
        hx, hz, ux, uz = self.hx[coasting], self.hz[coasting], self._goal_x[coasting], self._goal_z[coasting]
        near = hx * ux + hz * uz >= math.cos(step)
        rx, rz = _rotate_toward(hx, hz, ux, uz, step)
        self.hx[coasting] = np.where(near, ux, rx)
        self.hz[coasting] = np.where(near, uz, rz)
        self._coast_turn[coasting[near]] = False

    def _pivot(self, a, turned: np.ndarray, hx0: np.ndarray, hz0: np.ndarray, weights) -> None:
        """Shift the agents `turned` (indices into the group `a`) so that they turned about the foot they
        stand on (turn_about_planted_foot); `weights`: the group's idle, walk and run weights."""
        if not turned.size or not self.config.plant_feet:
            return
        kind = a.kind[turned] if len(self.motions) > 1 else np.zeros(len(turned), np.int8)
        for k, m in enumerate(self.motions):  # each character pivots on its own feet
            if m.pivots is None:
                continue
            mine = turned if len(self.motions) == 1 else turned[kind == k]
            if not mine.size:
                continue
            dx, dz = turn_about_planted_foot(m, a.phase[mine], [w[mine] for w in weights], hx0[mine], hz0[mine],
                                             a.hx[mine], a.hz[mine], a.scale[mine])
            x, z = self._inside(a.x[mine] + dx, a.z[mine] + dz)
            if self.obstacles is not None:  # (a pivot by a wall must not step into it: this comes after the apply phase's clearing)
                x, z = self.keep_out(x, z)
            a.x[mine], a.z[mine] = x, z

    def _inside(self, x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ground positions clamped into the world square (a pivot at its edge must not step out)."""
        e = self.half_extent
        return (np.minimum(np.maximum(x, self.origin[0] - e), self.origin[0] + e),
                np.minimum(np.maximum(z, self.origin[1] - e), self.origin[1] + e))

    def _bound(self, lo: int, hi: int) -> None:
        """World bounds for agents lo..hi: clamp, and stop the velocity component that points out."""
        for p, v, o in ((self.x[lo:hi], self.vx[lo:hi], self.origin[0]), (self.z[lo:hi], self.vz[lo:hi], self.origin[1])):
            low, high = o - self.half_extent, o + self.half_extent
            out = np.flatnonzero((p < low) | (p > high))
            if out.size:
                p[out] = np.minimum(np.maximum(p[out], low), high)
                v[out] = 0.0

    # -- obstacles

    def _free_share(self) -> float:
        return 1.0 if self.obstacles is None else self.obstacles.free_share

    def keep_out(self, x, z, iterations: int = 4) -> tuple[np.ndarray, np.ndarray]:
        """Points (x, z) moved out along the obstacle field's gradient until CLEARANCE from every
        obstacle (each move aims 5 mm past it: the field is bilinear, not linear), and into the world;
        a point in a corner between two obstacles steps out of both in a few moves."""
        x, z = np.array(x, np.float64), np.array(z, np.float64)
        o, e = self.obstacles, self.half_extent
        ox, oz = self.origin
        for _ in range(iterations):
            d = o.distance(x, z)
            near = np.flatnonzero(d < CLEARANCE)
            if not near.size:
                break
            gx, gz = o.gradient(x[near], z[near])
            move = CLEARANCE + 0.005 - d[near]
            x[near] = np.minimum(np.maximum(x[near] + gx * move, ox - e), ox + e)
            z[near] = np.minimum(np.maximum(z[near] + gz * move, oz - e), oz + e)
        return x, z

    def _clear_obstacles(self, lo: int, hi: int) -> None:
        """Agents lo..hi out of the obstacles (CLEARANCE from each), and their velocity into them stopped:
        they slide along a wall instead of pressing into it. A nearest-cell look first, so only the
        agents near an obstacle pay for the bilinear field and its gradient."""
        o = self.obstacles
        x, z = self.x[lo:hi], self.z[lo:hi]
        near = np.flatnonzero(o.cell_distance(x, z) < CLEARANCE + o.cell)
        if not near.size:
            return
        cx, cz = self.keep_out(x[near], z[near])
        moved = (cx != x[near]) | (cz != z[near])
        if not moved.any():
            return
        agents = near[moved]
        x[agents], z[agents] = cx[moved], cz[moved]
        gx, gz = o.gradient(x[agents], z[agents])
        vx, vz = self.vx[lo:hi], self.vz[lo:hi]
        into = np.minimum(vx[agents] * gx + vz[agents] * gz, 0.0)
        vx[agents] -= into * gx
        vz[agents] -= into * gz

    def _update_flow(self) -> None:
        """(The main process, before a substep's think.) Do FLOW_WORK units of the field toward the
        player's cell, started when the player has left the published field's cell and none is being
        made, and publish it into the shared arrays when it is done."""
        if self.obstacles is None:
            return
        cell = tuple(int(c) for c in np.floor(np.asarray(self.player, np.float64) / FLOW_CELL))
        if self._flow_job is None:
            if cell == self._flow_cell:
                return
            self._flow_job = (cell, flow_field_work(self.obstacles, cell))
        for _ in range(FLOW_WORK):
            field = next(self._flow_job[1])
            if field is not None:
                corner, step_i, step_j, usable = field
                self._flow_steps[0], self._flow_steps[1], self._flow_usable[...] = step_i, step_j, usable
                self._flow_corner[:] = corner[0], corner[1], 1.0
                self._flow_cell, self._flow_job = self._flow_job[0], None
                return

    def _flow_field(self) -> tuple | None:
        """The published flow field: (the window's first cell's corner (x, z), each cell's way down the
        path distances to the player: the neighbour (di, dj), and whether there is one); None without
        obstacles or before the first field is in."""
        if self.obstacles is None or not self._flow_corner[2]:
            return None
        return self._flow_corner[:2], self._flow_steps[0], self._flow_steps[1], self._flow_usable

    def _flow_directions(self, x: np.ndarray, z: np.ndarray, to_x: np.ndarray, to_z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Directions (unit, x and z) chasers at (x, z) take toward the player: toward the centre of their
        cell's way down the flow field where they are in its window and not within FLOW_DIRECT of the
        player, else straight (`to_x`, `to_z`: their offsets to the player)."""
        straight = np.hypot(to_x, to_z)
        ux, uz = to_x / np.maximum(straight, 1e-12), to_z / np.maximum(straight, 1e-12)
        flow = self._flow_field()
        if flow is None:
            return ux, uz
        corner, step_i, step_j, usable = flow
        i = np.floor((x - corner[0]) / FLOW_CELL).astype(np.int64)
        j = np.floor((z - corner[1]) / FLOW_CELL).astype(np.int64)
        inside = (i >= 1) & (i < FLOW_CELLS - 1) & (j >= 1) & (j < FLOW_CELLS - 1) & (straight > FLOW_DIRECT)
        k = np.flatnonzero(inside)
        if not k.size:
            return ux, uz
        i, j = i[k], j[k]
        # Toward that neighbour's centre from where the agent stands (not from its own cell's centre).
        tx = corner[0] + (i + step_i[i, j] + 0.5) * FLOW_CELL - x[k]
        tz = corner[1] + (j + step_j[i, j] + 0.5) * FLOW_CELL - z[k]
        norm = np.maximum(np.hypot(tx, tz), 1e-12)
        go = usable[i, j]
        ux[k] = np.where(go, tx / norm, ux[k])
        uz[k] = np.where(go, tz / norm, uz[k])
        return ux, uz

    def _wander(self, a, wandering: np.ndarray, h) -> None:
        a.pause -= h
        dx, dz = a.tx - a.x, a.tz - a.z
        idx = np.flatnonzero(wandering & (dx * dx + dz * dz < 0.16) & (a.pause <= 0.0))
        if idx.size:
            cfg = self.config
            draw = self._draws(a.ids(idx), _WANDER, 4)  # keyed by agent and substep (see _draws)
            angle = math.pi * (2.0 * draw[0] - 1.0)
            radius = cfg.wander_radius * np.sqrt(0.1 + 0.9 * draw[1])
            inner = self.half_extent - 0.5
            a.tx[idx] = np.clip(a.x[idx] + radius * np.sin(angle), self.origin[0] - inner, self.origin[0] + inner)
            a.tz[idx] = np.clip(a.z[idx] + radius * np.cos(angle), self.origin[1] - inner, self.origin[1] + inner)
            a.pause[idx] = np.where(draw[2] < 0.5, 1.0 + 3.0 * draw[3], 0.0)
            if self.obstacles is not None:  # a target in a building is moved out to the street beside it
                a.tx[idx], a.tz[idx] = self.keep_out(a.tx[idx], a.tz[idx])

    def _push_range(self, lo: int, hi: int, gain: float):
        """Separation pushes of agents lo..hi, from everyone's positions (nothing is moved here: the apply
        phase moves them, after every range has read the positions). Both agents of a pair closer than
        the separation radius r move apart by half the overlap, times `gain` (min(stiffness x h, 1)),
        and no agent moves more than r / 2. Every agent, every substep, the think budget's included: a
        pile-up must come apart as fast as without it (its agents think rarely, but they do not overlap
        for longer).

        An agent's entries in its range's list are contiguous and in the grid's order, so its push is a
        sum over the same entries in the same order whichever range it is in. Returns (agents, push x,
        push z) for the pushed ones, or None."""
        r = self.config.separation_radius
        first, second = self._range_list
        if not first.size:
            return None
        dx, dz = self.x[first] - self.x[second], self.z[first] - self.z[second]
        dist2 = dx * dx + dz * dz
        # Agents that died since the list was built are skipped here rather than by a rebuild.
        close = np.flatnonzero((dist2 < r * r) & (self.state[first] < DYING) & (self.state[second] < DYING))
        if not close.size:
            return None
        first, second = first[close], second[close]
        fx, fz = _overlap_push(first, second, dx[close], dz[close], np.sqrt(dist2[close]), r)
        local = first - lo  # sorted: the list is in agent order
        agents = local[np.flatnonzero(np.concatenate(([True], local[1:] != local[:-1])))]
        push_x = np.bincount(local, weights=fx, minlength=hi - lo)[agents]
        push_z = np.bincount(local, weights=fz, minlength=hi - lo)[agents]
        # Stiffness x h above 1 removes the whole overlap, never more; no agent moves more than r / 2.
        norm = np.sqrt(push_x * push_x + push_z * push_z) * gain
        gain = gain * np.minimum(1.0, 0.5 * r / np.maximum(norm, 1e-12))
        return agents + lo, push_x * gain, push_z * gain

    def _prepare_lists(self, moved2: float) -> bool:
        """Whether the separation's neighbour lists are to be rebuilt in this substep's push phase, and if
        so the grid they are built from (here, for the whole crowd: one sort). Each range's list holds,
        for each of its living agents, every living agent closer than the separation radius r and others
        up to 2r away. The lists are kept across substeps (a Verlet list, as in molecular dynamics)
        until some agent has moved r / 2 from where it stood when they were built (`moved2`: the largest
        squared move, measured by the think phase): until then no pair can have closed from over 2r to
        under r, so the lists still hold every close pair. A build costs about seven substeps' use of
        them; agents move 1 to 7 cm per substep."""
        r = self.config.separation_radius
        if self._pairs and moved2 <= 0.25 * r * r:
            return False
        self._params[P_SIDE] = self._build_grid(2.0 * r)
        self._pairs = True
        self.pair_builds += 1
        return True

    def _build_grid(self, size: float) -> int:
        """Living agents sorted into a uniform grid of `size`-wide cells (so every pair closer than `size`
        is in the same or adjacent cells): each one's cell, the agents in cell order and where each
        cell's agents start in it. Returns the grid's side in cells."""
        live = np.flatnonzero(self.state < DYING)
        everyone = live.size == self.n  # the usual case: plain arrays instead of gathers
        x, z = (self.x, self.z) if everyone else (self.x[live], self.z[live])
        # At most about 4 cells an agent: a separation radius far below the spacing (a valid setting)
        # must not ask for a grid of billions of cells; wider cells only find more candidates.
        size = max(size, 2.0 * self.half_extent / math.sqrt(4.0 * live.size + 1.0))
        side = int(math.ceil(2.0 * self.half_extent / size)) + 3  # spare cells around: no edge checks
        gx = np.minimum(np.maximum((x - (self.origin[0] - self.half_extent)) * (1.0 / size) + 1.0, 1.0), side - 2.0)
        gz = np.minimum(np.maximum((z - (self.origin[1] - self.half_extent)) * (1.0 / size) + 1.0, 1.0), side - 2.0)
        cell = gz.astype(np.int64) * side + gx.astype(np.int64)
        self._cell[live] = cell
        order = _sort_cells(cell, side * side)
        self._cell_order[: live.size] = order if everyone else live[order]
        cells = side * side + 1
        if self._pool is None:
            self._cell_first = np.zeros(cells, np.int64)
        else:
            if self._grid_block is None or self._grid_block.arrays["first"].size < cells:
                if self._grid_block is not None:
                    self._grid_block.close()
                self._grid_block = SharedArrays({"first": (np.int64, (cells + cells // 2,))})  # room to grow
                self._stale = True  # the workers map the new block before the push phase
            self._cell_first = self._grid_block.arrays["first"]
        self._cell_first[0] = 0
        np.cumsum(np.bincount(cell, minlength=side * side), out=self._cell_first[1:cells])
        return side

    def _build_list(self, lo: int, hi: int, side: int) -> None:
        """This range's neighbour list from the grid: for each living agent of lo..hi, in agent order,
        the agents of the three rows of three cells around its own (at most SEPARATION_CELL_CAP from
        each row), itself left out, within 2r. An agent's entries are the same whichever range it is
        in. Also notes where the range's agents stand, for the next substeps' move test."""
        r = self.config.separation_radius
        self._pairs_x[lo:hi], self._pairs_z[lo:hi] = self.x[lo:hi], self.z[lo:hi]
        live = lo + np.flatnonzero(self.state[lo:hi] < DYING)
        first_in = self._cell_first  # where each cell's agents start in the grid's order
        cell = self._cell[live]
        rows = np.stack([cell - side, cell, cell + side], axis=1)  # (agents, 3): the middle cell of each row
        start = first_in[rows - 1]
        count = np.minimum(first_in[rows + 2] - start, SEPARATION_CELL_CAP).ravel()
        start = start.ravel()
        total = int(count.sum())
        owner = np.repeat(np.repeat(live, 3), count)
        neighbour = self._cell_order[np.repeat(start - np.cumsum(count) + count, count) + np.arange(total)]
        dx, dz = self.x[owner] - self.x[neighbour], self.z[owner] - self.z[neighbour]
        keep = np.flatnonzero((dx * dx + dz * dz < 4.0 * r * r) & (owner != neighbour))
        self._range_list = (owner[keep], neighbour[keep])

    def neighbour_list(self) -> tuple[np.ndarray, np.ndarray]:
        """(agent, neighbour) entries of the list the last push phase used, for a crowd in one range (tests)."""
        if self.ranges() != 1:
            raise AIError("the neighbour list is split over the workers' ranges")
        return self._range_list

    # -- outputs

    def action_fade(self, agents: np.ndarray | None = None) -> np.ndarray:
        """0..1 per agent (or per agent of `agents`): how much of the action layer shows, cross-faded in
        and, except for death, out again."""
        action = self.action if agents is None else self.action[agents]
        elapsed = self.action_time if agents is None else self.action_time[agents]
        fade_len = max(self.config.crossfade, 1e-6)
        fade_in = np.minimum(elapsed * (1.0 / fade_len), 1.0)
        kind = self._kind_of(self, agents) if agents is not None else self._kind_of(self)
        fade_out = np.minimum(np.maximum((self.action_length(action, kind) - elapsed) * (1.0 / fade_len), 0.0), 1.0)
        fade = np.minimum(fade_in, np.where(action == ACT_DEATH, 1.0, fade_out))
        return np.where(action == NO_ACTION, 0.0, fade)

    def write_layers(self, out: np.ndarray | None = None) -> np.ndarray:
        """The processor's (N, 4, 4) float32 input: idle, walk, run, action, written into `out` in place,
        or into the AI's own array (None: no copy; the workers write it in shared memory). Returns it."""
        if out is not None and (out.shape != (self.n, LAYERS, 4) or out.dtype != np.float32):
            raise AIError(f"layers must be float32 ({self.n}, {LAYERS}, 4), got {out.dtype} {out.shape}")
        ranges = self._ready_ranges() if self.n else 1
        if ranges == 1:
            target = self._layer_out if out is None else out
            self._write_layer_range(target, 0, self.n)
            return target
        self._phase(WRITE_LAYERS, ranges)
        if out is None:
            return self._layer_out
        np.copyto(out, self._layer_out)
        return out

    def _write_layer_range(self, out: np.ndarray, lo: int, hi: int) -> None:
        """Layers of agents lo..hi. Most agents play no action, so the action layer is written for the
        acting ones only. In a cast of several characters each character's block takes its own clips."""
        first = cast_firsts(self.cast)
        for k, m in enumerate(self.motions):
            a, b = max(lo, int(first[k])), min(hi, int(first[k + 1]))
            if a < b:
                self._write_locomotion(out, a, b, k, m)
        acting = lo + np.flatnonzero(self.action[lo:hi])
        if acting.size:
            action = self.action[acting]
            kind = self._kind_of(self, acting)
            fade = self.action_fade(acting)
            mask = self._upper_mask[kind]
            upper = (action == ACT_ATTACK) & (mask >= 0)
            # Whole-body actions replace locomotion as they fade in; an upper-body action leaves the legs.
            out[acting, :3, WEIGHT] *= np.where(upper, 1.0, 1.0 - fade)[:, None]
            out[acting, 3, CLIP] = self._action_clip[kind, action]
            out[acting, 3, PHASE] = np.minimum(self.action_time[acting] / self.action_length(action, kind), 1.0)
            # Upper body: weight W against the locomotion's 1 gives the share W / (W + 1) = fade.
            out[acting, 3, WEIGHT] = np.where(upper, np.minimum(fade / np.maximum(1.0 - fade, 1e-12), MAX_ACTION_WEIGHT), fade)
            out[acting, 3, MASK] = np.where(upper, mask, -1)

    def _write_locomotion(self, out: np.ndarray, lo: int, hi: int, kind: int, m: Motion) -> None:
        """The locomotion layers of agents lo..hi, all of character `kind` (Motion `m`)."""
        # The constant columns copied from a run's worth of template (4x a broadcast's speed), then the
        # phase (rounded to float32 once) and the weights (each written by the operation that makes it)
        # into their strided columns, a run of agents at a time: each column is a strided pass over its
        # run, and a run of 16,384 agents' layers (1 MB) stays in the cache for all of them, where a
        # million agents' (64 MB) went through memory once per column.
        clips = tuple(m.clip[role] for role in ("idle", "walk", "run"))
        if self._layer_template.get(kind, (None,))[0] != clips:  # the first frame, or a new bake
            template = np.zeros((LAYER_RUN, LAYERS, 4), np.float32)
            template[:, :3, CLIP] = clips
            template[:, :, MASK] = -1.0
            self._layer_template[kind] = (clips, template)
        template = self._layer_template[kind][1]
        for start in range(lo, hi, LAYER_RUN):
            run = slice(start, min(start + LAYER_RUN, hi))
            o = out[run]
            o[:] = template[: len(o)]
            phase = self.phase[run].astype(np.float32)
            for layer in range(3):
                o[:, layer, PHASE] = phase
            vx, vz = self.vx[run], self.vz[run]
            locomotion_weights(m, np.sqrt(vx * vx + vz * vz), self.walk_top[run], self.speed_factor[run],
                               out=[o[:, layer, WEIGHT] for layer in range(3)])

    def layers(self) -> np.ndarray:
        return self.write_layers(np.empty((self.n, LAYERS, 4), np.float32))

    def instances(self, extra: int = 0) -> Instances:
        """The render's input: positions, headings, scales, tints, variants (fresh arrays, kept by the
        frame; the headings' arctangents are shared out to the workers, the rest is copies, over spans of
        agents side by side: crowd.spans). With `extra` > 0 every array has that many rows after the
        crowd's, zero, for the caller to fill (the survivor's), so nothing is copied twice to append
        them; with none, the scales and tints are the AI's own arrays."""
        n, rows = self.n, self.n + int(extra)
        pos = np.empty((rows, 3))
        yaw = np.empty(rows, np.float32)
        ranges = self._ready_ranges() if self.n else 1
        if ranges > 1:
            self._phase(HEADINGS, ranges)
        heads = any(m.head_count for m in self.motions)
        scale, tint = (self.scale, self.tint) if not extra else (np.empty(rows, np.float32), np.empty((rows, 4), np.uint8))
        head = self.head if not extra or not heads else np.empty(rows, self.head.dtype)

        def fill(lo: int, hi: int) -> None:
            pos[lo:hi, 0] = self.x[lo:hi]
            pos[lo:hi, 1] = 0.0
            pos[lo:hi, 2] = self.z[lo:hi]
            if ranges > 1:
                yaw[lo:hi] = self._yaw_out[lo:hi]
            else:
                np.arctan2(self.hx[lo:hi], self.hz[lo:hi], out=yaw[lo:hi], casting="same_kind")
            if extra:
                scale[lo:hi] = self.scale[lo:hi]
                tint[lo:hi] = self.tint[lo:hi]
                if heads:
                    head[lo:hi] = self.head[lo:hi]

        over_spans(fill, n)
        if extra:
            pos[n:], yaw[n:], scale[n:], tint[n:] = 0.0, 0.0, 0.0, 0
            if heads:
                head[n:] = 0
        variant = {"head": head} if heads else {}
        return Instances(pos, yaw, scale, tint, variant, None if len(self.cast) == 1 else self.cast)

    def check(self) -> list[str]:
        """Invariants every step must keep; empty when all hold (tests, and the stats' `ai_faults`)."""
        faults = []
        if any(not np.all(np.isfinite(a)) for a in (self.x, self.z, self.vx, self.vz, self.hx, self.hz, self.phase, self.action_time)):
            faults.append("non-finite agent state")
        slack = 1e-9 * max(1.0, float(np.max(np.abs(self.origin))))
        for p, o in ((self.x, self.origin[0]), (self.z, self.origin[1])):
            if self.n and (p.min() < o - self.half_extent - slack or p.max() > o + self.half_extent + slack):
                faults.append("agent outside the world bounds")
                break
        w = self.layers()[..., WEIGHT]
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            faults.append("layer weight not finite or negative")
        return faults

    def counts(self) -> dict[str, int]:
        return {name: int(np.count_nonzero(self.state == code)) for code, name in enumerate(STATE_NAMES)}


def locomotion_weights(m: Motion, speed: np.ndarray, walk: np.ndarray, speed_factor: np.ndarray, out=None):
    """(idle, walk, run weights, run share of the stride) from ground speed, for agents whose walk
    speeds are `walk` and run speeds `m.run_speed * speed_factor`:
    - from the walk's slowest playback (``m.walk_slowest`` of `walk`) up to `walk` the walk plays alone,
      slowed down (phase_rate), so its planted feet keep pace with the ground;
    - below that it blends with idle, at the slowest playback;
    - from `walk` to the run speed the walk blends into the run, one phase for both.
    `out`: three arrays (a layer's strided weight column, say) the weights are written into by the
    operations that make them, rounded once, instead of new arrays."""
    to_walk = np.minimum(speed / (m.walk_slowest * walk), 1.0)
    run_t = np.minimum(np.maximum((speed - walk) / (m.run_speed * speed_factor - walk), 0.0), 1.0)
    out = out or (None, None, None)
    return (np.subtract(1.0, to_walk, out=out[0], casting="unsafe"), np.multiply(to_walk, 1.0 - run_t, out=out[1], casting="unsafe"),
            np.multiply(to_walk, run_t, out=out[2], casting="unsafe"), run_t)


def blended_stride(m: Motion, run_t, scale=1.0):
    """Metres a cycle of the walk-run blend at run share `run_t`, for agents of size `scale`."""
    return (m.walk_stride + run_t * (m.run_stride - m.walk_stride)) * scale


def phase_rate(m: Motion, speed, walk, run_t, scale=1.0):
    """Cycles a second of the shared locomotion phase, for agents at `speed` whose walk speeds are
    `walk` and whose run shares are `run_t` (locomotion_weights): speed over the blended stride, so that
    a planted foot keeps pace with the ground. Below the walk's slowest playback the walk's weight
    falls instead of its rate, so the rate stays there: its planted foot, at that weight, still moves
    with the ground (idle's feet stand still). Standing agents play idle at its own rate. `scale`: the
    agents' sizes, which their strides grow with (the skinning shader scales the whole model)."""
    moving = np.maximum(speed, m.walk_slowest * walk) / blended_stride(m, run_t, scale)
    return np.where(speed > 0.0, moving, 1.0 / np.maximum(m.duration["idle"], 1e-3))


def locomotion_layers(m: Motion, speed: float, frames: int, dt: float, speed_factor: float = 1.0):
    """One agent walking straight at a steady `speed` (m/s) for `frames` frames `dt` apart, as the AI
    animates it (crowd.anim.foot_skate measures what its feet do): its (frames, 4, 4) float32 layers
    and the distance (frames,) float64 it has covered at each frame."""
    walk = np.array([m.walk_speed * speed_factor])
    speeds = np.array([float(speed)])
    w = locomotion_weights(m, speeds, walk, np.array([speed_factor]))
    rate = float(phase_rate(m, speeds, walk, w[3])[0])
    t = np.arange(frames) * dt
    layers = empty_layers(frames, LAYERS)
    for layer, role in enumerate(("idle", "walk", "run")):
        layers[:, layer, CLIP] = m.clip[role]
        layers[:, layer, PHASE] = np.mod(rate * t, 1.0)
        layers[:, layer, WEIGHT] = float(w[layer][0])
    return layers, speed * t


def _rotate_toward(hx, hz, ux, uz, step: float):
    """Unit headings (hx, hz) rotated by the angle `step` toward the unit directions (ux, uz)."""
    sin, cos = math.sin(step), math.cos(step)
    s = np.where(hx * uz - hz * ux >= 0.0, -sin, sin)  # toward the goal
    return cos * hx + s * hz, cos * hz - s * hx


def _overlap_push(i, j, dx, dz, dist, r: float):
    """Per overlapping pair (i, j) at offset (dx, dz) = i - j and distance `dist` < r: the push on i
    (j gets its opposite), half the overlap along the pair's direction."""
    inv = 1.0 / np.maximum(dist, 1e-12)
    ux, uz = dx * inv, dz * inv
    # Coincident agents: a direction made from the pair's agent numbers (deterministic), pointing from
    # the higher-numbered agent to the lower, so the pair's two entries push its agents apart.
    same = np.flatnonzero(dist < 1e-9)
    if same.size:
        low, high = np.minimum(i[same], j[same]), np.maximum(i[same], j[same])
        angle = 2 * math.pi * np.mod(low * 0.6180339887 + high * 0.7548776662, 1.0)
        sign = np.where(i[same] == low, 1.0, -1.0)
        ux[same], uz[same] = sign * np.cos(angle), sign * np.sin(angle)
    amount = 0.5 * (r - dist)  # each of the two takes half the overlap
    return ux * amount, uz * amount


def advance_phase(phase: np.ndarray, step, where=True) -> np.ndarray:
    """Advance float64 clip phases in place by `step` (cycles) and wrap them into [0, 1); `where`: only
    those phases (the others are left unwritten: another process may own them).

    Why phases and not a clock: a float32 clock of seconds has a 2 ms step after 10 hours (16 ms
    after 3 days), so phase = time / duration would jitter by whole key intervals; a wrapped float64
    phase keeps its 1e-16 resolution forever (crowd-bench error's "10 hours" case measures both)."""
    np.add(phase, step, out=phase, where=where)
    np.subtract(phase, np.floor(phase), out=phase, where=where)
    return phase


def _sort_cells(cell: np.ndarray, cells: int) -> np.ndarray:
    """Stable argsort of cell numbers. numpy sorts 16-bit keys by radix, about 15x faster than the
    comparison sort wider keys get, so wider numbers are sorted as two 16-bit digits, low digit first."""
    if cells <= 1 << 16:
        return np.argsort(cell.astype(np.uint16), kind="stable")
    if cells > 1 << 32:
        return np.argsort(cell, kind="stable")
    low = np.argsort((cell & 0xFFFF).astype(np.uint16), kind="stable")
    return low[np.argsort((cell[low] >> 16).astype(np.uint16), kind="stable")]
