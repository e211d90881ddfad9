"""Foot lock: a foot that carries weight stays where it came down (issue 21, point 2).

The clips plant their feet for an agent walking straight at the clip's speed. What is left is what
the clips cannot know: the body turning over a planted foot, neighbours pushing it, and blends of two
gaits whose feet do not move together (docs/ACCURACY.md, "Foot skate"). The lock removes it in the
processor, after the layers are blended and before the hierarchy is composed:

- **Legs.** Every joint named like a foot or an ankle (not a toe or a ball) under a knee under a hip
  is a leg's ankle (at most MAX_LEGS legs, none sharing a joint); where none is named so, a leg is told
  by its shape (``find_legs``). Its toe is the child the foot points to. A joint is *down* within
  CONTACT_M of the lowest height it reaches in the bake's looping clips.
- **Input,** per agent and frame, one vec4: its ground step since the last frame (computed by the CPU
  in float64), and its front (sin and cos of its yaw) times its scale: no trigonometry on the CPU, and
  16 bytes an agent (0.26 ms for 100,000 agents where yaw and scale apart cost 3.5 ms).
- **State,** per agent and leg, one vec4 in a GPU buffer: FREE (the correction still carried, decaying
  as exp(-dt / RELEASE_S)), HELD (the ankle's point and the foot's world yaw, held), HELD_TOE (the toe's
  point: the heel is up and the foot rolls about its toe, as the clip has it), or STEPPING (where the
  ankle left the ground and its yaw, and the step's progress). Points are horizontal offsets in world
  orientation from the agent's ground point, which the CPU moves by the agent's ground step (computed
  in float64, so a world far from the origin costs no float32 precision).
- **The correction** is a turn of the foot about its ankle, then a shift, that puts its held point
  where it is held. A leg holds while its ankle or toe is down and its foot is not pointing near
  vertically (a yaw is defined); it engages at its *corrected* position, so engaging never moves a
  foot, and a leg that lifts keeps its correction and lets it decay in the air.
- **A step.** A held foot more than STEP_SHIFT_M (times the agent's scale) from where its clip puts
  it, or turned more than STEP_TWIST_RAD, steps where every other leg is held (the body stands on
  them); beyond HOLD_SHIFT_M or HOLD_TWIST_RAD it steps anyway, a hop (dragging it along instead slid
  it a few centimetres a frame: the crowd's foot skate was measured both ways, docs/ACCURACY.md). A
  step takes STEP_S: the foot rises STEP_LIFT_M and comes down, and moves from where it left to where
  its clip puts it in the middle half, while it is clear of the ground. A correction beyond RESET_M or
  RESET_RAD (a respawn, a teleport) is dropped.
- **The leg.** Where the correction is above CORRECTION_EPS (or the foot is lifted), the ankle's
  target is the animated ankle moved by it (its height is the clip's, plus a step's lift), the foot
  turns about the vertical, and the hip and knee are solved to the target (``solve_leg``, two-bone IK
  keeping the knee's bend plane). Below it nothing is solved: a planted straight walk, the error
  report's poses and every agent with the lock off get the processor's palette bit for bit.

The GPU runs this in shaders/foot_lock.glsl (compute path only: the fragment path keeps no state);
``FootLockTwin`` is its float64 twin, the same steps in the same order: change one, change the other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..asset.model import CONTACT_M, ModelError, Skeleton
from ..asset.pose import global_matrices, rest_pose
from .bake import AnimationBake

__all__ = ["CONTACT_M", "CORRECTION_EPS", "HOLD_SHIFT_M", "HOLD_TWIST_RAD", "MAX_LEGS", "RELEASE_S", "STEP_LIFT_M", "STEP_S",
           "STEP_SHIFT_M", "STEP_TWIST_RAD", "FootLockTwin", "Legs", "bake_legs", "find_legs", "solve_leg"]

MAX_LEGS = 4
# A held foot further than this from where its clip puts it (metres scale with the agent), or turned
# further, steps back under the body where every other leg stands held...
STEP_SHIFT_M = 0.15
STEP_TWIST_RAD = 0.6
# ...and while another is in the air, it stays held up to these, and hops beyond them.
HOLD_SHIFT_M = 0.30
HOLD_TWIST_RAD = 0.9
RESET_M = 0.6  # a correction this large is a respawn or a teleport, not a foot that slid
RESET_RAD = 1.5
RELEASE_S = 0.08  # a released correction decays with this time constant
STEP_S = 0.2  # a foot held too far steps back under the body in this long
STEP_LIFT_M = 0.08  # and rises this high (times the agent's scale) at the middle of its step
# A leg state's 4th component: FREE, HELD (the ankle's point held), HELD_TOE (the toe's: the heel is up),
# or STEPPING + the step's progress in [0, 1).
FREE, HELD, HELD_TOE, STEPPING = 0.0, 1.0, 2.0, 3.0
NO_TOE = -1e30  # the "lowest height" of a toe a foot does not have: never in contact
CORRECTION_EPS = 1e-6  # metres and radians: below it the leg is left as the clips put it
# A foot whose forward axis is this close to vertical has no yaw worth holding.
MIN_FORWARD_HORIZONTAL = 0.25
FOOT_WORDS = ("foot", "ankle")
LEG_SHAPE_LOW, LEG_SHAPE_RISE = 0.15, 0.15  # legs told by their shape (_legs_by_shape): shares of the skeleton's height
NOT_ANKLE_WORDS = ("toe", "ball", "ik", "end", "tip")


@dataclass
class Legs:
    """The legs the lock holds: per leg (hip's parent or -1, hip, knee, ankle), its toe (the ankle's
    child the foot points to, or -1), the foot's forward axis in the ankle's rest-pose frame, and the lowest
    heights of its ankle and toe (model space, metres)."""

    joints: np.ndarray  # (K, 4) int32
    toe: np.ndarray  # (K,) int32, -1 where the foot has none
    forward: np.ndarray  # (K, 3) float64: towards the toe (else model +Z) in the ankle's rest-pose frame, unit
    lowest: np.ndarray  # (K, 2) float64: the ankle's and the toe's lowest height in the bake's looping clips
    names: tuple

    def __len__(self) -> int:
        return len(self.names)


def bake_legs(skeleton: Skeleton, bake: AnimationBake) -> Legs:
    """The skeleton's legs, each ankle's and toe's lowest height taken over every key of the bake's
    looping clips (idle and locomotion: where feet carry weight); the bind pose's where none loops."""
    legs = find_legs(skeleton)
    if not len(legs):
        return legs
    joints = np.unique(np.concatenate([legs.joints[:, 3], legs.toe[legs.toe >= 0]]))
    heights = [np.full(len(joints), np.inf)]
    bind = np.linalg.inv(bake.inverse_bind())[joints]
    for c, info in enumerate(bake.clips):
        if info.loop and info.frame_count > 1:
            skin = bake.skinning_matrices(c, np.arange(info.frame_count) / (info.frame_count - 1))[:, joints]
            heights.append(np.einsum("fkij,kj->fki", skin, bind[:, :, 3])[..., 1].min(axis=0))
    lowest = np.min(heights, axis=0)
    return find_legs(skeleton, {int(j): float(h) for j, h in zip(joints, lowest) if np.isfinite(h)})


def find_legs(skeleton: Skeleton, heights=None) -> Legs:
    """The skeleton's legs (at most MAX_LEGS, the lowest ankles in the rest pose first): joints named like
    a foot or an ankle under a knee under a hip; where none is named so (CesiumMan's "leg_joint_L_3"),
    any joint near the ground whose parent and grandparent each stand well above the one below
    (``_legs_by_shape``). `heights` maps an ankle or toe joint to its lowest model-space height in the
    clips; without it the rest pose's height is used. Positions are the rest pose's in model space, as
    the processor composes it (a root's own turn included: CesiumMan's file is Z-up)."""
    names = [n.lower() for n in skeleton.names]
    parents = np.asarray(skeleton.parents)
    rest = global_matrices(skeleton, rest_pose(skeleton))[0]
    found = []
    for j, name in enumerate(names):
        if not any(w in name for w in FOOT_WORDS) or any(w in name for w in NOT_ANKLE_WORDS):
            continue
        knee = int(parents[j])
        hip = int(parents[knee]) if knee >= 0 else -1
        if hip < 0 or any(any(w in names[k] for w in FOOT_WORDS) for k in (knee, hip)):
            continue  # no leg above it, or a helper under another foot joint
        thigh = np.linalg.norm(rest[knee, :3, 3] - rest[hip, :3, 3])
        shin = np.linalg.norm(rest[j, :3, 3] - rest[knee, :3, 3])
        if min(thigh, shin) < 1e-4 * max(thigh, shin, 1e-12):
            continue  # a bone of no length: nothing to bend
        found.append((rest[j, 1, 3], j, knee, hip))
    if not found:
        found = _legs_by_shape(parents, rest)
    # Each leg's ankle rewrites its hip, knee and ankle while the other legs read their own chains to
    # the root (on the GPU, at the same time): a leg that shares a joint with another's chain is left out.
    kept, used, chains = [], set(), set()
    for entry in sorted(found):
        _, j, knee, hip = entry
        ancestors = set()
        p = int(parents[hip])
        while p >= 0:
            ancestors.add(p)
            p = int(parents[p])
        if len(kept) < MAX_LEGS and not ({hip, knee, j} & (used | chains)) and not (ancestors & used):
            kept.append(entry)
            used |= {hip, knee, j}
            chains |= ancestors
    found = kept
    joints = np.array([(parents[hip], hip, knee, j) for _, j, knee, hip in found], np.int32).reshape(-1, 4)
    forward = np.zeros((len(found), 3))
    toe = np.full(len(found), -1, np.int32)
    lowest = np.zeros((len(found), 2))
    heights = heights or {}
    for i, (y, j, _, _) in enumerate(found):
        # The foot's forward axis: towards its toe where it has one (the joint that stays down as the
        # heel lifts), else the model's front; in the ankle's rest-pose frame.
        rot = rest[j, :3, :3] / np.linalg.norm(rest[j, :3, 0])
        toes = [c for c in range(len(names)) if parents[c] == j and np.hypot(*(rest[c, [0, 2], 3] - rest[j, [0, 2], 3])) > 1e-6]
        axis = np.array([0.0, 0.0, 1.0]) if not toes else rest[toes[0], :3, 3] - rest[j, :3, 3]
        forward[i] = rot.T @ (axis / np.linalg.norm(axis))
        if toes:
            toe[i] = toes[0]
        lowest[i] = heights.get(j, y), heights.get(toes[0], rest[toes[0], 1, 3]) if toes else NO_TOE
    return Legs(joints, toe, forward, lowest, tuple(skeleton.names[j] for _, j, _, _ in found))


def _legs_by_shape(parents: np.ndarray, rest: np.ndarray) -> list:
    """Legs told by their shape: an ankle in the lowest LEG_SHAPE_LOW of the skeleton's height whose knee
    stands at least LEG_SHAPE_RISE of that height above it and whose hip as much above the knee."""
    y = rest[:, 1, 3]
    span = float(y.max() - y.min())
    if not span > 0.0:
        return []
    found = []
    for j in range(len(parents)):
        knee = int(parents[j])
        hip = int(parents[knee]) if knee >= 0 else -1
        if hip < 0 or y[j] > y.min() + LEG_SHAPE_LOW * span:
            continue
        if y[knee] - y[j] >= LEG_SHAPE_RISE * span and y[hip] - y[knee] >= LEG_SHAPE_RISE * span:
            found.append((y[j], j, knee, hip))
    return found


def _rotation(axis: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations about unit `axis` (N, 3) by the angle whose cosine and sine are `c` and `s` (Rodrigues)."""
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    t = 1.0 - c
    return np.stack([np.stack([t * x * x + c, t * x * y - s * z, t * x * z + s * y], -1),
                     np.stack([t * x * y + s * z, t * y * y + c, t * y * z - s * x], -1),
                     np.stack([t * x * z - s * y, t * y * z + s * x, t * z * z + c], -1)], axis=1)


def _yaw_rotation(angle: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations about +Y whose front (0, 0, 1) turns to (sin a, 0, cos a), as an agent's yaw."""
    c, s = np.cos(angle), np.sin(angle)
    zero, one = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, zero, s], -1), np.stack([zero, one, zero], -1), np.stack([-s, zero, c], -1)], axis=1)


def _unit(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = np.linalg.norm(v, axis=-1)
    return v / np.where(n > 0.0, n, 1.0)[..., None], n


def _cos_sin(c):
    """(cosine, sine) of an angle in [0, pi] from its cosine (clamped to [-1, 1])."""
    c = np.clip(c, -1.0, 1.0)
    return c, np.sqrt(np.maximum(1.0 - c * c, 0.0))


def _difference(a, b):
    """(cosine, sine) of angle a minus angle b, each given as its (cosine, sine)."""
    return a[0] * b[0] + a[1] * b[1], a[1] * b[0] - a[0] * b[1]


def _smootherstep(t):
    return t * t * t * (t * (6.0 * t - 15.0) + 10.0)


def wrap_angle(a):
    """Into [-pi, pi)."""
    return a - 2.0 * np.pi * np.floor((a + np.pi) / (2.0 * np.pi))


def solve_leg(hip_parent_rot, hip_global, knee_global, ankle_global, target, twist):
    """Two-bone IK for N legs (float64). Globals are (N, 4, 4) model-space matrices (uniform scale
    allowed), `hip_parent_rot` (N, 3, 3) the hip's parent's global rotation, `target` (N, 3) where the
    ankle must go, `twist` (N,) radians about +Y the foot turns by. Returns the (N, 3, 3) rotations
    that pre-multiply the hip's, the knee's and the ankle's local linear parts (their translations
    stay): the knee keeps its bend plane, the ankle reaches the target where the leg reaches it (else
    the leg points at it, straight), and the foot keeps its model-space orientation turned by `twist`."""
    h, k, a = hip_global[:, :3, 3], knee_global[:, :3, 3], ankle_global[:, :3, 3]
    thigh = np.linalg.norm(k - h, axis=1)
    shin = np.linalg.norm(a - k, axis=1)
    low, high = np.abs(thigh - shin) + 1e-5 * (thigh + shin), (thigh + shin) * (1.0 - 1e-5)
    # The triangle's angles from its sides, before and after, by one formula: a correction of 0 turns
    # nothing, in float32 too (the angle between two vectors by acos did not, near a straight knee).
    # No angle is taken at all: each turn is its cosine and sine, from the sides (a GPU's acos is
    # allowed to be rough: llvmpipe's is 1.6e-4 rad off, 0.1 mm at the end of a leg). The target's
    # reach stays inside the leg's, or where the clip's own already is outside it.
    now = np.linalg.norm(a - h, axis=1)
    then = np.clip(np.linalg.norm(target - h, axis=1), np.minimum(low, now), np.maximum(high, now))
    # Between the thigh and the hip-to-ankle line, and the knee's inner angle: then minus now.
    hip_delta = _difference(_cos_sin((thigh * thigh + then * then - shin * shin) / (2.0 * thigh * then)),
                            _cos_sin((thigh * thigh + now * now - shin * shin) / (2.0 * thigh * now)))
    knee_delta = _difference(_cos_sin((thigh * thigh + shin * shin - then * then) / (2.0 * thigh * shin)),
                             _cos_sin((thigh * thigh + shin * shin - now * now) / (2.0 * thigh * shin)))
    bend, bend_len = _unit(np.cross(a - h, k - h))  # the knee's bend plane's normal
    hip_x = _unit(hip_global[:, :3, 0])[0]
    bend = np.where((bend_len > 1e-9 * thigh * (thigh + shin))[:, None], bend, hip_x)  # a straight leg: the hip's own x axis
    # The swing from the ankle's line to the target's: its cosine and sine from the dot and cross
    # products (acos of a dot product near 1 turned float32 rounding of 6e-8 into 3.5e-4 rad).
    cross = np.cross(a - h, target - h)
    swing_axis, swing_len = _unit(cross)
    swings = swing_len > 1e-12 * thigh * thigh
    dot = np.sum((a - h) * (target - h), axis=1)
    norm = np.hypot(swing_len, dot)
    swing = (np.where(swings, dot / np.where(norm > 0, norm, 1.0), 1.0), np.where(swings, swing_len / np.where(norm > 0, norm, 1.0), 0.0))
    swing_axis = np.where(swings[:, None], swing_axis, bend)
    hip_turn = _rotation(swing_axis, *swing) @ _rotation(bend, *hip_delta)  # about the hip, in model space
    knee_turn = _rotation(bend, *knee_delta)  # about the knee, before the hip's turn
    hip_rot = hip_global[:, :3, :3] / np.linalg.norm(hip_global[:, :3, 0], axis=1)[:, None, None]
    knee_rot = knee_global[:, :3, :3] / np.linalg.norm(knee_global[:, :3, 0], axis=1)[:, None, None]
    parent_t = np.swapaxes(hip_parent_rot, 1, 2)
    q_hip = parent_t @ hip_turn @ hip_parent_rot
    q_knee = np.swapaxes(hip_rot, 1, 2) @ knee_turn @ hip_rot
    q_ankle = np.swapaxes(knee_rot, 1, 2) @ np.swapaxes(knee_turn, 1, 2) @ np.swapaxes(hip_turn, 1, 2) @ _yaw_rotation(twist) @ knee_rot
    return q_hip, q_knee, q_ankle


class FootLockTwin:
    """The float64 twin of the GPU foot lock (shaders/foot_lock.glsl), holding its own state."""

    def __init__(self, legs: Legs, agents: int = 0):
        self.legs = legs
        self.state = np.zeros((agents, len(legs), 4))

    def resize(self, agents: int) -> None:
        """Agents kept keep their state; new ones start free with nothing carried (as the GPU's)."""
        state = np.zeros((agents, len(self.legs), 4))
        keep = min(agents, len(self.state))
        state[:keep] = self.state[:keep]
        self.state = state

    def apply(self, local: np.ndarray, parents, motion: np.ndarray, dt: float) -> np.ndarray:
        """Advance the state by one frame and return the locked locals (N, J, 4, 4) float64. `local`
        is the blended local pose (N, J, 4, 4), `motion` (N, 4): the agent's ground step since the last
        frame (x, z) and its front (x, z: sin and cos of its yaw) times its scale; `dt` the simulated
        seconds of the frame."""
        local = np.array(local, np.float64)
        n = local.shape[0]
        if n != len(self.state):
            raise ModelError(f"the foot lock holds {len(self.state)} agents, got a pose of {n}")
        motion = np.asarray(motion, np.float64).reshape(n, 4)
        step = motion[:, :2]
        scale = np.hypot(motion[:, 2], motion[:, 3])
        sy, cy = motion[:, 2] / scale, motion[:, 3] / scale  # the front: (sin yaw, cos yaw)
        yaw = np.arctan2(sy, cy)
        dt = max(float(dt), 0.0)
        decay = math.exp(-dt / RELEASE_S)

        def world(v):  # model-space (x, z) of (N, 3) points or vectors -> world orientation, metres
            return scale[:, None] * np.stack([cy * v[:, 0] + sy * v[:, 2], -sy * v[:, 0] + cy * v[:, 2]], 1)

        for k, (hip_parent, hip, knee, ankle) in enumerate(self.legs.joints):
            parent = _global(local, parents, hip_parent) if hip_parent >= 0 else np.tile(np.eye(4), (n, 1, 1))
            g_hip = parent @ local[:, hip]
            g_knee = g_hip @ local[:, knee]
            g_ankle = g_knee @ local[:, ankle]
            p = g_ankle[:, :3, 3]
            toe = self.legs.toe[k]
            t = (g_ankle @ local[:, toe])[:, :3, 3] if toe >= 0 else p
            forward = g_ankle[:, :3, :3] @ self.legs.forward[k]
            has_yaw = np.hypot(forward[:, 0], forward[:, 2]) > MIN_FORWARD_HORIZONTAL * np.linalg.norm(forward, axis=1)
            foot_yaw = yaw + np.arctan2(forward[:, 0], forward[:, 2])
            ankle_w, toe_w = world(p), world(t - p)  # the animated ankle from the ground point; the toe from the ankle
            # In contact: within CONTACT_M (world metres) of the lowest height.
            ankle_down = p[:, 1] <= self.legs.lowest[k, 0] + CONTACT_M / scale
            toe_down = t[:, 1] <= self.legs.lowest[k, 1] + CONTACT_M / scale
            s = self.state[:, k]
            mode = s[:, 3]
            stepping = mode >= STEPPING
            kept = (mode == HELD) | (mode == HELD_TOE) | stepping  # a point held (a stepping foot's: where it left)
            # The correction: a turn of the foot about its ankle by c_yaw, then a shift by c_xy, that
            # puts the held point (the ankle's, or the toe's) where it is held.
            cyaw = np.where(kept, wrap_angle(s[:, 2] - foot_yaw), s[:, 2] * decay)
            hold_xy = s[:, :2] - step
            cxy = np.where(kept[:, None], hold_xy - np.where((mode == HELD_TOE)[:, None], _turn(toe_w, cyaw), 0.0) - ankle_w, s[:, :2] * decay)
            reset = (np.hypot(cxy[:, 0], cxy[:, 1]) > RESET_M * scale) | (np.abs(cyaw) > RESET_RAD)
            cxy, cyaw = np.where(reset[:, None], 0.0, cxy), np.where(reset, 0.0, cyaw)
            # A step: the foot rises and comes down (a half sine of STEP_LIFT_M) and moves from where it
            # left to where its clip puts it (smootherstep) in the middle half, where it is above 0.7 of
            # the lift, clear of the ground: until then it stays where it was (moving with the clip from the
            # start, the toe slid 2 mm a frame as it rose).
            progress = np.where(stepping, mode - STEPPING + dt / STEP_S, 0.0)
            landed = stepping & ((progress >= 1.0) | reset)
            ease = np.where(stepping, 1.0 - _smootherstep(np.clip((progress - 0.25) * 2.0, 0.0, 1.0)), 1.0)
            cxy, cyaw = cxy * ease[:, None], cyaw * ease
            lift = np.where(stepping & ~landed, STEP_LIFT_M * np.sin(np.pi * np.minimum(progress, 1.0)), 0.0) / scale
            hold = (ankle_down | toe_down) & has_yaw
            # Held too far: the foot steps where every other leg is held (the earlier legs' states are this
            # frame's, the later ones' the last frame's, as on the GPU), and beyond the hold limits anyway.
            shift = np.hypot(cxy[:, 0], cxy[:, 1])
            over = hold & ~stepping & ((shift > STEP_SHIFT_M * scale) | (np.abs(cyaw) > STEP_TWIST_RAD))
            others = [j for j in range(len(self.legs)) if j != k]
            planted = np.all(np.isin(self.state[:, others, 3], (HELD, HELD_TOE)), axis=1) if others else np.ones(n, bool)
            start = over & (planted | (shift > HOLD_SHIFT_M * scale) | (np.abs(cyaw) > HOLD_TWIST_RAD))
            hold &= ~stepping | landed
            # Held by the ankle while it is down (the foot flat, or its heel striking), else by the toe.
            by_toe = hold & ~ankle_down
            point = ankle_w + cxy + np.where(by_toe[:, None], _turn(toe_w, cyaw), 0.0)
            held = np.column_stack([point, wrap_angle(foot_yaw + cyaw), np.where(by_toe, HELD_TOE, HELD)])
            leaving = np.column_stack([ankle_w + cxy, wrap_angle(foot_yaw + cyaw), np.full(n, STEPPING)])
            free = np.column_stack([cxy, cyaw, np.full(n, FREE)])
            self.state[:, k] = np.where(start[:, None], leaving,
                                        np.where((stepping & ~landed)[:, None], np.column_stack([hold_xy, s[:, 2], STEPPING + progress]),
                                                 np.where(hold[:, None], held, free)))
            shift = np.hypot(cxy[:, 0], cxy[:, 1])
            act = (shift > CORRECTION_EPS * scale) | (np.abs(cyaw) > CORRECTION_EPS) | (lift > 0.0)
            if not np.any(act):
                continue
            # The correction in model space: world orientation turned back by the yaw, over the scale.
            dx = (cy * cxy[:, 0] - sy * cxy[:, 1]) / scale
            dz = (sy * cxy[:, 0] + cy * cxy[:, 1]) / scale
            target = p + np.stack([dx, lift, dz], 1)
            parent_rot = parent[:, :3, :3] / np.linalg.norm(parent[:, :3, 0], axis=1)[:, None, None]
            q_hip, q_knee, q_ankle = solve_leg(parent_rot, g_hip, g_knee, g_ankle, target, cyaw)
            for joint, q in ((hip, q_hip), (knee, q_knee), (ankle, q_ankle)):
                local[act, joint, :3, :3] = q[act] @ local[act, joint, :3, :3]
        return local


def _turn(v: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """World (x, z) vectors (N, 2) turned by `angle` about +Y, as an agent's yaw turns its front."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1]], 1)


def _global(local: np.ndarray, parents, joint: int) -> np.ndarray:
    """(N, 4, 4) model-space matrix of one joint: its chain to the root composed."""
    g = local[:, joint]
    p = int(parents[joint])
    while p >= 0:
        g = local[:, p] @ g
        p = int(parents[p])
    return g
