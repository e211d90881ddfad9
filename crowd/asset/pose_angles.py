"""The clips' pose parameters: named angles and a hips offset, turned into joint rotations, and eased
key poses over them."""

from __future__ import annotations

import math

import numpy as np

from .. import transforms as tf
from .model import Skeleton
from .pose import LocalPose, global_matrices
from .rig import ZOMBIE_BODY, Body, _joint_positions

# A pose is a handful of named angles (radians) and a hips offset (metres); clips are functions
# of phase p in [0, 1) that return those parameters, turned into joint rotations by _pose_to_joints.
# Conventions at rest (world-aligned joint axes): a positive *_pitch leans forward, thigh_flex swings
# the leg forward, knee bends the shin back, ankle points the toes down, arm_down lowers the arm from
# the T-pose, arm_fwd swings it forward, elbow bends the forearm, wrist droops the hand.

_PARAMS = (
    "hips_x hips_y hips_z hips_pitch hips_yaw hips_roll spine_pitch spine_yaw chest_pitch chest_yaw chest_roll "
    "neck_pitch head_pitch head_roll head_yaw jaw"
).split()
_SIDE_PARAMS = "shrug arm_down arm_fwd arm_twist elbow wrist thigh_flex thigh_twist thigh_abd knee ankle toe".split()
TAU = 2.0 * math.pi


def _neutral(n: int) -> dict[str, np.ndarray]:
    p = {k: np.zeros(n) for k in _PARAMS}
    for s in "lr":
        for k in _SIDE_PARAMS:
            p[f"{k}_{s}"] = np.zeros(n)
        p[f"arm_down_{s}"] = np.full(n, 1.3)  # arms hang by default
        p[f"elbow_{s}"] = np.full(n, 0.25)
    return p


def _q(x=0.0, y=0.0, z=0.0, order="xyz") -> np.ndarray:
    qx = tf.quat_from_axis_angle([1.0, 0.0, 0.0], np.asarray(x, dtype=np.float64))
    qy = tf.quat_from_axis_angle([0.0, 1.0, 0.0], np.asarray(y, dtype=np.float64))
    qz = tf.quat_from_axis_angle([0.0, 0.0, 1.0], np.asarray(z, dtype=np.float64))
    if order == "xyz":  # apply x, then y, then z
        return tf.quat_mul(qz, tf.quat_mul(qy, qx))
    if order == "xzy":  # apply x, then z, then y
        return tf.quat_mul(qy, tf.quat_mul(qz, qx))
    raise ValueError(order)


def _mirror(q: np.ndarray) -> np.ndarray:
    """Mirror a left-side rotation to the right side (reflection through the YZ plane)."""
    q = q.copy()
    q[..., 1] *= -1.0
    q[..., 2] *= -1.0
    return q


def _pose_to_joints(p: dict[str, np.ndarray], n: int, body: Body = ZOMBIE_BODY) -> tuple[dict[str, np.ndarray], np.ndarray]:
    p = {k: np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)).copy() for k, v in p.items()}
    out = {
        "hips": _q(p["hips_pitch"], p["hips_yaw"], p["hips_roll"], "xzy"),
        "spine": _q(p["spine_pitch"], p["spine_yaw"], 0.0),
        "chest": _q(p["chest_pitch"], p["chest_yaw"], p["chest_roll"]),
        "neck": _q(p["neck_pitch"], 0.5 * p["head_yaw"], 0.0),
        "head": _q(p["head_pitch"], 0.5 * p["head_yaw"], p["head_roll"]),
        "jaw": _q(p["jaw"], 0.0, 0.0),
    }
    for s in "lr":
        g = lambda k: p[f"{k}_{s}"]
        shoulder = _q(0.0, -0.3 * g("arm_fwd") * 0.3, 0.4 * g("shrug"))
        # Twist about the bone, then lower, then swing forward (in the shoulder's frame).
        arm = _q(g("arm_twist"), -g("arm_fwd"), -g("arm_down"), "xzy")
        forearm = _q(0.0, -g("elbow"), 0.0)
        hand = _q(0.0, 0.0, -g("wrist"))
        thigh = _q(-g("thigh_flex"), g("thigh_twist"), g("thigh_abd"))
        shin = _q(g("knee"), 0.0, 0.0)
        foot = _q(g("ankle"), 0.0, 0.0)
        toe = _q(g("toe"), 0.0, 0.0)
        for name, q in (("shoulder", shoulder), ("upper_arm", arm), ("forearm", forearm), ("hand", hand),
                        ("thigh", thigh), ("shin", shin), ("foot", foot), ("toe", toe)):
            out[f"{name}_{s}"] = q if s == "l" else _mirror(q)
    hips_t = np.stack([p["hips_x"], p["hips_y"], p["hips_z"]], axis=1) + _joint_positions(body)[0]
    return out, hips_t


def _bump(p, centre, width):
    """A smooth periodic bump in phase, peaking at `centre`."""
    d = np.mod(p - centre + 0.5, 1.0) - 0.5
    return np.exp(-((d / width) ** 2))


def _ease_keys(p, times, values):
    """Piecewise ease-in-out between key poses (times in [0, 1], values per key)."""
    p = np.asarray(p, dtype=np.float64)
    out = np.empty_like(p)
    for i, x in enumerate(p):
        k = int(np.clip(np.searchsorted(times, x, side="right") - 1, 0, len(times) - 2))
        u = (x - times[k]) / (times[k + 1] - times[k])
        u = float(np.clip(u, 0.0, 1.0))
        u = u * u * (3 - 2 * u)
        out[i] = values[k] + (values[k + 1] - values[k]) * u
    return out


def _keyed(p, keys: list[tuple[float, dict[str, float]]], base: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Override parameters with eased key poses; a key lists only the parameters it changes."""
    names = set().union(*(k[1].keys() for k in keys))
    for name in names:
        times, vals, last = [], [], None
        for t, pose in keys:
            last = pose.get(name, last if last is not None else float(np.ravel(base[name])[0]))
            times.append(t)
            vals.append(last)
        base[name] = _ease_keys(p, np.array(times), np.array(vals))
    return base


def _globals(skeleton: Skeleton, joints: dict[str, np.ndarray], hips_t: np.ndarray) -> np.ndarray:
    """Model-space joint matrices (n, J, 4, 4) of n keys of joint rotations and hips positions."""
    n = hips_t.shape[0]
    rot = np.broadcast_to(skeleton.rest_rotation, (n,) + skeleton.rest_rotation.shape).copy()
    for name, q in joints.items():
        rot[:, skeleton.index(name)] = q
    tr = np.broadcast_to(skeleton.rest_translation, (n,) + skeleton.rest_translation.shape).copy()
    tr[:, 0] = hips_t
    return global_matrices(skeleton, LocalPose(tr, rot, np.ones(tr.shape)))
