"""The built-in characters' rig: the zombie's joints and hierarchy, its weapon socket, and Body, a build
of that rig with its joints standing elsewhere at rest (crowd.asset.brute makes a heavier one)."""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from .. import transforms as tf
from .model import Skeleton
from .pose import global_matrices, rest_pose

# The joints: (name, parent, rest position in model space)
_JOINTS = [
    ("hips", None, (0.0, 0.98, 0.0)),
    ("spine", "hips", (0.0, 1.10, -0.01)),
    ("chest", "spine", (0.0, 1.28, -0.015)),
    ("neck", "chest", (0.0, 1.50, -0.01)),
    ("head", "neck", (0.0, 1.60, 0.0)),
    ("jaw", "head", (0.0, 1.63, 0.035)),
    ("shoulder_l", "chest", (0.03, 1.44, -0.01)),
    ("upper_arm_l", "shoulder_l", (0.18, 1.44, -0.01)),
    ("forearm_l", "upper_arm_l", (0.46, 1.44, -0.01)),
    ("hand_l", "forearm_l", (0.71, 1.44, -0.01)),
    ("shoulder_r", "chest", (-0.03, 1.44, -0.01)),
    ("upper_arm_r", "shoulder_r", (-0.18, 1.44, -0.01)),
    ("forearm_r", "upper_arm_r", (-0.46, 1.44, -0.01)),
    ("hand_r", "forearm_r", (-0.71, 1.44, -0.01)),
    ("hand_r_socket", "hand_r", (-0.79, 1.435, -0.01)),
    ("thigh_l", "hips", (0.10, 0.93, 0.0)),
    ("shin_l", "thigh_l", (0.10, 0.51, 0.005)),
    ("foot_l", "shin_l", (0.10, 0.09, -0.01)),
    ("toe_l", "foot_l", (0.10, 0.025, 0.125)),
    ("thigh_r", "hips", (-0.10, 0.93, 0.0)),
    ("shin_r", "thigh_r", (-0.10, 0.51, 0.005)),
    ("foot_r", "shin_r", (-0.10, 0.09, -0.01)),
    ("toe_r", "foot_r", (-0.10, 0.025, 0.125)),
]
JOINT_NAMES = tuple(j[0] for j in _JOINTS)
SOCKET_JOINT = "hand_r_socket"
# Socket frame relative to the hand: +Y (handle) -> model +Z, +Z (out of the palm) -> model -Y.
SOCKET_ROTATION = tf.quat_from_axis_angle([1.0, 0.0, 0.0], math.pi / 2)


@dataclasses.dataclass(frozen=True)
class Body:
    """A build of the generator's skeleton (its joints, names and hierarchy always the zombie's): where
    the joints stand at rest, and what the planted-feet clips and the grounding need of its feet. The
    zombie is ``ZOMBIE_BODY``; crowd.asset.brute makes a heavier one."""

    joints: tuple  # (name, parent, rest position in model space), in _JOINTS' order
    stance_ankle_y: float = 0.085  # the ankle joint's height with the foot flat: its lowest sole point (see heel, tip) at y = 0
    toe_from_ankle: tuple = (0.0, -0.065, 0.135)  # the toe joint from the foot joint at rest
    heel: tuple = (0.0, -0.055, -0.06)  # a sole point under the heel, in the foot joint's frame
    tip: tuple = (0.0, -0.02, 0.06)  # a sole point under the toes' tip, in the toe joint's frame
    stance_width: float = 0.11  # the ankles' distance from the midline when standing

    def positions(self) -> np.ndarray:
        return np.array([j[2] for j in self.joints], dtype=np.float64)


ZOMBIE_BODY = Body(tuple(_JOINTS))


def _joint_positions(body: Body = ZOMBIE_BODY) -> np.ndarray:
    return body.positions()


def build_skeleton(body: Body = ZOMBIE_BODY) -> Skeleton:
    names = JOINT_NAMES
    parents = np.array([-1 if p is None else names.index(p) for _, p, _ in body.joints], dtype=np.int32)
    pos = _joint_positions(body)
    local_t = np.array([pos[i] - (pos[p] if p >= 0 else 0.0) for i, p in enumerate(parents)])
    rot = tf.quat_identity((len(names),))
    rot[names.index(SOCKET_JOINT)] = SOCKET_ROTATION
    skel = Skeleton(names, parents, local_t, rot, np.ones((len(names), 3)), np.tile(np.eye(4), (len(names), 1, 1)))

    bind = global_matrices(skel, rest_pose(skel))[0]
    skel.inverse_bind = np.linalg.inv(bind)
    return skel.validate()


@functools.cache
def _skeleton(body: Body = ZOMBIE_BODY) -> Skeleton:
    """The skeleton the clips are authored on (read only)."""
    return build_skeleton(body)
