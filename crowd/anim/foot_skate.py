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

from dataclasses import dataclass

import numpy as np

from ..asset.model import Skeleton

CONTACT_M = 0.03  # metres above a joint's lowest point within which it is in contact with the ground
SKATE_SPEED_M_S = 0.10  # a contact frame step faster than this counts as skating
FOOT_WORDS = ("foot", "ankle", "toe", "ball")


class SkateError(ValueError):
    """Bad input to the foot-skate measure; the message is one line."""


def foot_joints(skeleton: Skeleton) -> list[int]:
    """The joints named like a foot, an ankle, a toe or a ball, in skeleton order."""
    return [j for j, name in enumerate(skeleton.names) if any(word in name.lower() for word in FOOT_WORDS)]


def joint_positions(matrices: np.ndarray, skeleton: Skeleton, joints) -> np.ndarray:
    """(F, K, 3) model-space positions of `joints` from skinning matrices (F, J, 3|4, 4) (the palette, or
    the reference's): each matrix applied to its joint's bind-pose position."""
    joints = np.asarray(joints, np.int64)
    bind = np.linalg.inv(skeleton.inverse_bind[joints])[:, :3, 3]  # (K, 3) joint positions at bind time
    m = np.asarray(matrices, np.float64)[:, joints, :3, :]
    return np.einsum("fkij,kj->fki", m[..., :3], bind) + m[..., 3]


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


def measure(world: np.ndarray, dt: float, walked_m: float, names) -> FootSkate:
    """The foot skate of foot-joint trajectories `world` (F, K, 3) in metres, `dt` seconds apart, over
    which the agent walked `walked_m` metres."""
    world = np.asarray(world, np.float64)
    if world.ndim != 3 or world.shape[2] != 3 or world.shape[0] < 2 or world.shape[1] != len(names) or not len(names):
        raise SkateError(f"foot skate needs (frames >= 2, feet >= 1, 3) positions, got {world.shape} for {len(names)} feet")
    if not np.all(np.isfinite(world)):
        raise SkateError("foot skate: a foot position is not finite")
    if not (np.isfinite(dt) and dt > 0) or not (np.isfinite(walked_m) and walked_m >= 0):
        raise SkateError(f"foot skate needs dt > 0 and a distance >= 0, got {dt!r} and {walked_m!r}")
    height = world[..., 1]
    contact = height <= height.min(axis=0) + CONTACT_M
    both = contact[1:] & contact[:-1]  # (F - 1, K): steps between two contact frames
    step = np.linalg.norm(world[1:][..., [0, 2]] - world[:-1][..., [0, 2]], axis=2)
    slide = np.where(both, step, 0.0).sum(axis=0)  # metres per joint
    contact_time = both.sum(axis=0) * dt
    steps = int(both.sum())
    per_m = 100.0 * slide / walked_m if walked_m > 0 else np.full(len(names), np.nan)
    return FootSkate(
        slide_cm_per_m=float(np.mean(per_m)), worst_cm_per_m=float(np.max(per_m)),
        slide_cm_per_s=float(100.0 * slide.sum() / contact_time.sum()) if contact_time.sum() > 0 else 0.0,
        share_over=float(np.count_nonzero(both & (step > SKATE_SPEED_M_S * dt)) / steps) if steps else 0.0,
        contact_share=float(steps / both.size), walked_m=float(walked_m),
        per_joint={str(n): round(float(v), 4) for n, v in zip(names, per_m)})
