"""Foot skate: how far a foot that carries weight slides over the ground (issue 21, point 1).

Definition (docs/ACCURACY.md, "Foot skate"):
- the feet are the skeleton's joints named like a foot, an ankle, a toe or a ball (``foot_joints``);
- a foot joint is in contact in a frame when it is within ``CONTACT_M`` (3 cm) above its lowest point
  over the sequence measured (a clip's cycle, or a run of frames of one agent);
- its slide in a frame step is its horizontal displacement in world space between two frames in both of
  which it is in contact; world space is the skinning palette (the GPU's, or the float64 reference's)
  applied to the joint's bind position, then the agent's own transform (position, heading, scale), so
  the agent's actual ground speed is in it;
- reported per metre the agent walked (cm/m: a foot that slides 1 cm per metre loses 1 cm of ground
  for every metre the body covers), as a speed (cm/s, for standing clips, which walk nowhere), and as
  the share of contact frame steps whose horizontal speed is over ``SKATE_SPEED_M_S`` (10 cm/s).

Research code measures the same thing this way (a foot below a few centimetres moving faster than a
threshold); none of the crowd systems this project compares with reports it.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from ..errors import CrowdError
from ..asset.model import CONTACT_M, Skeleton, foot_joints
from .palette_reference import palette_joint_positions

__all__ = ["CONTACT_M", "SKATE_SPEED_M_S", "FootSkate", "FootSkateMonitor", "SkateError", "contact_steps", "foot_joints",
           "joint_positions", "measure", "to_world"]
SKATE_SPEED_M_S = 0.10  # a contact frame step faster than this counts as skating


class SkateError(CrowdError, ValueError):
    """Bad input to the foot-skate measure; the message is one line."""


def joint_positions(matrices: np.ndarray, skeleton: Skeleton, joints) -> np.ndarray:
    """(F, K, 3) model-space positions of `joints` from skinning matrices (F, J, 3|4, 4) (the palette, or
    the reference's): each matrix applied to its joint's bind-pose position."""
    joints = np.asarray(joints, np.int64)
    return palette_joint_positions(np.asarray(matrices)[:, joints, :3, :], skeleton.inverse_bind[joints])


def to_world(model: np.ndarray, ground: np.ndarray, yaw, scale=1.0) -> np.ndarray:
    """(F, K, 3) world positions of model-space points (F, K, 3) of an agent standing at `ground` (F, 2)
    float64 (x, z), turned by `yaw` about +Y (its front is (sin yaw, cos yaw)) and scaled by `scale`,
    as the skinning shader places it."""
    yaw = np.broadcast_to(np.asarray(yaw, np.float64), (model.shape[0],))[:, None]
    s, c = np.sin(yaw), np.cos(yaw)
    x, y, z = (model[..., i] * scale for i in range(3))
    return np.stack([c * x + s * z + ground[:, 0:1], y, -s * x + c * z + ground[:, 1:2]], axis=-1)


@dataclass
class FootSkate:
    """One sequence's foot skate; the crowd's figures are the mean and the largest over its feet."""

    slide_cm_per_m: float  # mean over the foot joints of their contact slide, per metre walked (nan: walked nowhere)
    worst_cm_per_m: float  # the foot joint that slid most
    slide_cm_per_s: float  # mean contact slide per second of contact
    share_over: float  # share of contact frame steps over SKATE_SPEED_M_S, all foot joints together
    contact_share: float  # share of frame steps in contact, all foot joints together
    walked_m: float
    per_joint: dict  # joint name -> slide in cm per metre walked

    def as_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def measure(world: np.ndarray, dt, walked_m: float, names) -> FootSkate:
    """The foot skate of foot-joint trajectories `world` (F, K, 3) in metres, `dt` seconds apart (one
    number, or one per frame step: (F - 1,)), over which the agent walked `walked_m` metres."""
    world = np.asarray(world, np.float64)
    if world.ndim != 3 or world.shape[2] != 3 or world.shape[0] < 2 or world.shape[1] != len(names) or not len(names):
        raise SkateError(f"foot skate needs (frames >= 2, feet >= 1, 3) positions, got {world.shape} for {len(names)} feet")
    if not np.all(np.isfinite(world)):
        raise SkateError("foot skate: a foot position is not finite")
    dt = np.broadcast_to(np.asarray(dt, np.float64), (world.shape[0] - 1,)) if np.ndim(dt) == 0 else np.asarray(dt, np.float64)
    if dt.shape != (world.shape[0] - 1,) or not np.all(np.isfinite(dt) & (dt > 0)) or not (np.isfinite(walked_m) and walked_m >= 0):
        raise SkateError(f"foot skate needs dt > 0 for each of the {world.shape[0] - 1} steps and a distance >= 0, got {walked_m!r}")
    dt = dt[:, None]
    both, step = contact_steps(world)
    slide = np.where(both, step, 0.0).sum(axis=0)  # metres per joint
    contact_time = np.where(both, dt, 0.0).sum(axis=0)
    steps = int(both.sum())
    per_m = 100.0 * slide / walked_m if walked_m > 0 else np.full(len(names), np.nan)
    return FootSkate(
        slide_cm_per_m=float(np.mean(per_m)), worst_cm_per_m=float(np.max(per_m)),
        slide_cm_per_s=float(100.0 * slide.sum() / contact_time.sum()) if contact_time.sum() > 0 else 0.0,
        share_over=float(np.count_nonzero(both & (step > SKATE_SPEED_M_S * dt)) / steps) if steps else 0.0,
        contact_share=float(steps / both.size), walked_m=float(walked_m),
        per_joint={str(n): round(float(v), 4) for n, v in zip(names, per_m)})


def contact_steps(world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For foot-joint trajectories (F, K, 3) in world space: which frame steps (F - 1, K) are between two
    frames in contact (within CONTACT_M of the joint's lowest point over the sequence), and each step's
    horizontal move in metres (F - 1, K)."""
    height = world[..., 1]
    contact = height <= height.min(axis=0) + CONTACT_M
    step = np.linalg.norm(world[1:][..., [0, 2]] - world[:-1][..., [0, 2]], axis=2)
    return contact[1:] & contact[:-1], step


class FootSkateMonitor:
    """The running crowd's foot skate, from a small read-back: `sample` agents, spread over the crowd,
    have their foot joints read back with the weapons' sockets through the same ring, never waited for
    (crowd.draw.readback), and composed with the transforms those agents had in the frame read. Each
    sampled agent keeps a window of its last `window` frames; a frame missing from the ring, a respawn,
    or anything but locomotion (an action, dying) starts its window again, so every window is one steady
    stretch of walking or running."""

    def __init__(self, skeleton: Skeleton, sample: int = 32, window: int = 240, min_walk_m: float = 0.5):
        self.feet = foot_joints(skeleton)
        self.names = [skeleton.names[j] for j in self.feet]
        self._inverse_bind = skeleton.inverse_bind[self.feet]
        self.sample, self.window, self.min_walk_m = int(sample), int(window), float(min_walk_m)
        self._sent: dict[int, tuple] = {}  # frame -> (agents, ground (k, 2), yaw (k,), scale (k,), time)
        # The last `window` frames read, each whole: (frame, time, agents (k,), ground (k, 2), feet world (k, K, 3)),
        # oldest first; and where each sampled agent's stretch began. A frame is kept as its arrays, not
        # split per agent: the windows are cut out of them only when the summary is asked for.
        self._frames: deque = deque(maxlen=self.window)
        self._since: dict[int, int] = {}

    def reset(self) -> None:
        """Forget every window (a new crowd: the same agent numbers are other agents now)."""
        self._sent.clear()
        self._frames.clear()
        self._since.clear()

    def entries(self, agents: int, steady) -> tuple[np.ndarray, np.ndarray]:
        """(agents, joints) to gather this frame: the sampled agents that are in steady locomotion
        (`steady(indices)`: a bool for each) times the foot joints."""
        picked = self.sampled(agents)
        picked = picked[steady(picked)] if picked.size else picked
        self.walking(picked)
        return np.repeat(picked, len(self.feet)), np.tile(np.asarray(self.feet, np.int64), picked.size)

    def sampled(self, agents: int) -> np.ndarray:
        """The sample's agents among `agents` (spread over them), walking or not; none without feet."""
        if not self.feet or not self.sample or not agents:
            return np.zeros(0, np.int64)
        return np.unique(np.linspace(0, agents - 1, min(self.sample, agents)).astype(np.int64))

    def walking(self, agents: np.ndarray) -> None:
        """The sampled agents in steady locomotion now: the others' stretches end here."""
        for a in set(self._since) - set(np.asarray(agents).tolist()):
            del self._since[a]

    def sent(self, frame: int, agents: np.ndarray, ground: np.ndarray, yaw: np.ndarray, scale: np.ndarray, time: float) -> None:
        """The transforms of the agents whose feet were gathered in `frame` (one entry per agent)."""
        self._sent[frame] = (agents, np.asarray(ground, np.float64), np.asarray(yaw, np.float64), np.asarray(scale, np.float64), float(time))
        for old in [f for f in self._sent if f < frame - 8]:
            del self._sent[old]  # frames whose read-back never came (a reset ring)

    def received(self, frame: int, rows: np.ndarray) -> None:
        """The foot rows (k x K, 3, 4) read back for `frame`, in the order ``entries`` gave."""
        sent = self._sent.pop(frame, None)
        if sent is None or not len(sent[0]):
            return
        agents, ground, yaw, scale, t = sent
        k = len(self.feet)
        model = palette_joint_positions(np.asarray(rows).reshape(len(agents), k, 3, 4), self._inverse_bind)
        world = to_world(model, ground, yaw, scale[:, None])
        # An agent continues its stretch only from the frame before (a frame missing: it starts again).
        before = set(self._frames[-1][2].tolist()) if self._frames and self._frames[-1][0] == frame - 1 else set()
        for a in agents.tolist():
            if a not in before or a not in self._since:
                self._since[a] = frame
        self._frames.append((frame, t, np.asarray(agents), np.asarray(ground, np.float64), world))

    def tracks(self) -> dict[int, list]:
        """Each sampled agent's window: (frame, time, ground (2,), feet world (K, 3)), oldest first."""
        out: dict[int, list] = {a: [] for a in self._since}
        for frame, t, agents, ground, world in self._frames:
            for i, a in enumerate(agents.tolist()):
                if a in out and frame >= self._since[a]:
                    out[a].append((frame, t, ground[i], world[i]))
        return {a: track for a, track in out.items() if track}

    def summary(self) -> dict | None:
        """The crowd's foot skate over the sampled agents' windows that walked at least min_walk_m:
        mean and worst slide (cm per metre walked), and the share of contact steps over the speed
        threshold; None while no window has walked that far."""
        results = []
        for track in self.tracks().values():
            if len(track) < 3:
                continue
            t = np.array([e[1] for e in track])
            ground = np.array([e[2] for e in track])
            walked = float(np.linalg.norm(np.diff(ground, axis=0), axis=1).sum())
            if walked < self.min_walk_m or np.any(np.diff(t) <= 0):
                continue
            results.append(measure(np.array([e[3] for e in track]), np.diff(t), walked, self.names))
        if not results:
            return None
        return {"agents": len(results), "slide_cm_per_m": round(float(np.mean([r.slide_cm_per_m for r in results])), 4),
                "worst_cm_per_m": round(float(np.max([r.worst_cm_per_m for r in results])), 4),
                "share_over": round(float(np.mean([r.share_over for r in results])), 4),
                "walked_m": round(float(np.sum([r.walked_m for r in results])), 3),
                "contact_m": CONTACT_M, "skate_speed_m_s": SKATE_SPEED_M_S}
