"""Planted feet: each foot's path over a gait cycle, still in world space while it carries weight, and
the legs' angles solved for it by inverse kinematics."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .. import transforms as tf
from .model import Skeleton
from .pose_angles import _globals, _pose_to_joints, _q
from .rig import ZOMBIE_BODY, Body, _skeleton

# Planted feet (issue 21, point 2). The legs of the locomotion clips and of idle are not keyed by angle:
# each foot follows a path in model space that keeps it still in world space while it carries weight,
# and the leg's angles are solved for it by inverse kinematics. Keyed angles had let feet slide 33 cm
# for every metre walked (docs/ACCURACY.md, "Foot skate").
#
# The path of one foot over a cycle, for a body moving forward at `stride` metres a cycle:
# - stance, for `duty` of the cycle around its mid-stance phase: flat on the ground, still in world
#   space, so in model space it moves backward at exactly the body's speed;
# - swing: for the first and last `lift` share of the swing it rises (or comes down) straight up in
#   world space, still over the same spot; in between it travels forward one stride, toes pitched down.
# A foot below the contact height (3 cm above its lowest) therefore never moves horizontally in world
# space, which is what crowd-bench skate measures (the 30 fps keys' interpolation leaves 0.4 to 0.6
# cm/m). Both clips keep their mid-stances at the same phases, so that in a walk-run blend (one phase
# for both) their stance feet move together.


@dataclasses.dataclass(frozen=True)
class _Gait:
    stride: float  # metres the body covers a cycle (the clip's stride)
    duty: float  # share of the cycle a foot carries weight
    lift: float  # share of the swing, at each end, in which the foot moves only up or down
    mid_stance: float  # phase of the left foot's mid-stance; the right one's is half a cycle later
    height: tuple[float, float]  # swing height of the ankle (left, right), metres
    toe_down: tuple[float, float]  # toes-down pitch at mid-swing (left, right), radians
    toe_out: tuple[float, float]  # yaw of each foot, toes outward, radians
    width: float = 0.10  # the feet's distance from the midline
    reach: float = 0.0  # model-space z of the ankle at mid-stance
    direction: float = 0.0  # radians from +Z (forward) toward +X (the left) that the body travels: pi / 2 steps sideways to the left


def _smootherstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _foot_path(g: _Gait, side: int, p: np.ndarray, body: Body = ZOMBIE_BODY) -> tuple[np.ndarray, np.ndarray]:
    """Model-space targets (n, 3) of one foot's ankle and toe joints at phases `p` (side 0 left, 1 right)."""
    mid = g.mid_stance + 0.5 * side
    delta = np.mod(p - mid + 0.5, 1.0) - 0.5  # phase since mid-stance, in [-0.5, 0.5)
    stance = np.abs(delta) <= 0.5 * g.duty
    u = np.where(stance, 0.0, np.mod(delta - 0.5 * g.duty, 1.0) / (1.0 - g.duty))  # share of the swing done
    travel = _smootherstep((u - g.lift) / (1.0 - 2.0 * g.lift))  # share of the stride travelled in world space
    since_mid = np.where(stance, delta, 0.5 * g.duty + u * (1.0 - g.duty))  # body travel since mid-stance, cycles
    d = g.stride * (travel - since_mid)  # the foot's travel from its mid-stance place, along the body's direction
    z = g.reach + math.cos(g.direction) * d
    # Straight up (or down) to the swing's height, which clears the contact height at once even in a
    # blend that gives this clip a small weight, then forward in a low arc.
    rise = np.minimum(_smootherstep(u / g.lift), _smootherstep((1.0 - u) / g.lift))
    rise = np.where(stance, 0.0, rise)
    y = body.stance_ankle_y + g.height[side] * rise * (1.0 + 0.25 * np.sin(math.pi * travel))
    sign = 1.0 if side == 0 else -1.0
    ankle = np.stack([sign * g.width + math.sin(g.direction) * d, y, z], axis=1)
    pitch = np.where(stance, 0.0, g.toe_down[side] * np.sin(math.pi * travel) ** 2)
    return ankle, _toe_of(ankle, pitch, np.full_like(p, sign * g.toe_out[side]), body)


def _toe_of(ankle: np.ndarray, pitch, yaw, body: Body = ZOMBIE_BODY) -> np.ndarray:
    """Where the toe joint is for a foot at `ankle` (n, 3), pitched toes down by `pitch` and turned by `yaw`."""
    return ankle + tf.quat_rotate(_q(pitch, yaw, 0.0), np.array(body.toe_from_ankle))


def _leg(skeleton: Skeleton, s: str) -> tuple[int, float, float]:
    """A leg's thigh joint and its upper and lower bone lengths (side "l" or "r")."""
    length = lambda name: float(np.linalg.norm(skeleton.rest_translation[skeleton.index(f"{name}_{s}")]))
    return skeleton.index(f"thigh_{s}"), length("shin"), length("foot")


def _hip_joints(skeleton: Skeleton, a: dict[str, np.ndarray], n: int, body: Body = ZOMBIE_BODY) -> list[np.ndarray]:
    """Model-space positions (n, 3) of the left and right thigh joints under the pose `a`."""
    rot, hips_t = _pose_to_joints(a, n, body)
    g = _globals(skeleton, rot, hips_t)
    return [g[:, _leg(skeleton, s)[0], :3, 3] for s in "lr"]


_LEG_PARAMS = ("thigh_flex", "thigh_twist", "thigh_abd", "knee", "ankle")


def _guess_legs(skeleton: Skeleton, a: dict[str, np.ndarray], targets, n: int, body: Body = ZOMBIE_BODY) -> None:
    """A starting point for _plant, in place: each leg bent in its own plane, knee forward, as the law
    of cosines gives it for the hip-to-ankle distance (hips rotation ignored; the solver corrects it)."""
    hips = _hip_joints(skeleton, a, n, body)  # the leg's own angles do not move its hip joint
    toe_from_ankle = body.toe_from_ankle
    for side, s in enumerate("lr"):
        _, upper, lower = _leg(skeleton, s)
        d = targets[side][0] - hips[side]
        dist = np.clip(np.linalg.norm(d, axis=1), abs(upper - lower) + 1e-3, upper + lower - 1e-4)
        bend = math.pi - np.arccos((upper * upper + lower * lower - dist * dist) / (2 * upper * lower))
        lean = np.arcsin(np.clip(lower * np.sin(bend) / dist, -1.0, 1.0))  # thigh ahead of the hip-ankle line
        a[f"thigh_flex_{s}"] = np.arctan2(d[:, 2], -d[:, 1]) + lean
        a[f"knee_{s}"] = bend
        a[f"thigh_abd_{s}"] = np.zeros(n)
        a[f"thigh_twist_{s}"] = np.zeros(n)
        toe = targets[side][1] - targets[side][0]
        pitch = np.arctan2(-toe[:, 1], toe[:, 2]) - math.atan2(-toe_from_ankle[1], toe_from_ankle[2])
        a[f"ankle_{s}"] = pitch - (a["hips_pitch"] - a[f"thigh_flex_{s}"] + bend)


def _plant(p: np.ndarray, a: dict[str, np.ndarray], targets, iterations: int = 200, body: Body = ZOMBIE_BODY) -> dict[str, np.ndarray]:
    """Solve both legs' angles (`_LEG_PARAMS`) so that the ankle and toe joints reach `targets`
    ((ankle, toe) per side, each (n, 3)), with the rest of the pose `a` as it is, starting from
    _guess_legs (which picks the knee-forward solution). Damped Gauss-Newton on a numerical Jacobian:
    the generator runs once, and the two legs are independent, so one pose evaluation perturbs the same
    angle of both."""
    skeleton = _skeleton(body)
    n = p.shape[0]
    joints = [[skeleton.index(f"foot_{s}"), skeleton.index(f"toe_{s}")] for s in "lr"]
    goal = np.stack([np.concatenate(t, axis=1) for t in targets])  # (2, n, 6)

    def residual(params):
        rot, hips_t = _pose_to_joints(params, n, body)
        g = _globals(skeleton, rot, hips_t)
        return np.stack([np.concatenate([g[:, j, :3, 3] for j in js], axis=1) for js in joints]) - goal

    a = {k: np.array(v, dtype=np.float64, copy=True) for k, v in a.items()}
    _guess_legs(skeleton, a, targets, n, body)
    eps, eye = 1e-6, np.eye(len(_LEG_PARAMS))
    damping = np.full((2, n), 1e-3)  # Levenberg-Marquardt: per side and key, lowered on success
    r = residual(a)
    cost = np.sum(r * r, axis=-1)
    for _ in range(iterations):
        if np.max(np.abs(r)) < 1e-9:
            break
        jac = np.empty((2, n, 6, len(_LEG_PARAMS)))
        for k, name in enumerate(_LEG_PARAMS):
            moved = dict(a)
            for s in "lr":
                moved[f"{name}_{s}"] = a[f"{name}_{s}"] + eps
            jac[..., k] = (residual(moved) - r) / eps
        jt = np.swapaxes(jac, -1, -2)
        jtj = jt @ jac
        step = np.linalg.solve(jtj + damping[..., None, None] * eye, -(jt @ r[..., None]))[..., 0]
        trial = dict(a)
        for i, s in enumerate("lr"):
            for k, name in enumerate(_LEG_PARAMS):
                trial[f"{name}_{s}"] = a[f"{name}_{s}"] + step[i, :, k]
        r_trial = residual(trial)
        cost_trial = np.sum(r_trial * r_trial, axis=-1)
        better = cost_trial < cost
        for i, s in enumerate("lr"):
            for name in _LEG_PARAMS:
                key = f"{name}_{s}"
                a[key] = np.where(better[i], trial[key], a[key])
        r = np.where(better[..., None], r_trial, r)
        cost = np.where(better, cost_trial, cost)
        damping = np.where(better, damping / 3.0, damping * 4.0)
    worst = float(np.max(np.abs(residual(a))))
    if worst > 1e-6:  # a foot out of the leg's reach: the gait's hips are too high for its stride
        raise AssertionError(f"the legs do not reach their feet: {worst * 1000:.3f} mm off")
    return a


def _planted(p: np.ndarray, a: dict[str, np.ndarray], gait: _Gait, body: Body = ZOMBIE_BODY) -> dict[str, np.ndarray]:
    targets = [_foot_path(gait, side, p, body) for side in (0, 1)]
    a = dict(a)
    a["hips_y"] = np.asarray(a["hips_y"], np.float64) - _reach_drop(a, targets, p.shape[0], body=body)
    return _plant(p, a, targets, body=body)


def _reach_drop(a: dict[str, np.ndarray], targets, n: int, slack: float = 0.985, body: Body = ZOMBIE_BODY) -> np.ndarray:
    """How far to lower the hips at each key of a loop so that both ankles are within `slack` of the
    leg's full length (a straight knee is a singular, snapping pose): the largest need nearby, smoothed,
    so the hips do not jerk."""
    skeleton = _skeleton(body)
    hips = _hip_joints(skeleton, a, n, body)
    need = np.zeros(n)
    for side, s in enumerate("lr"):
        _, upper, lower = _leg(skeleton, s)
        leg = slack * (upper + lower)
        d = targets[side][0] - hips[side]
        flat = np.minimum(d[:, 0] ** 2 + d[:, 2] ** 2, leg * leg)
        need = np.maximum(need, np.maximum(0.0, -d[:, 1] - np.sqrt(leg * leg - flat)))
    widened = np.max([np.roll(need, k) for k in range(-3, 4)], axis=0)
    return np.mean([np.roll(widened, k) for k in range(-2, 3)], axis=0)


def _standing(p: np.ndarray, a: dict[str, np.ndarray], toe_out=(0.12, 0.2), reach=(0.02, -0.03), body: Body = ZOMBIE_BODY) -> dict[str, np.ndarray]:
    """Both feet flat and still where they stand (idle sways its hips over them)."""
    targets = []
    for side in (0, 1):
        sign = 1.0 if side == 0 else -1.0
        ankle = np.tile([sign * body.stance_width, body.stance_ankle_y, reach[side]], (p.shape[0], 1))
        targets.append((ankle, _toe_of(ankle, 0.0, np.full(p.shape, sign * toe_out[side]), body)))
    return _plant(p, a, targets, body=body)


def _foot_markers(g: _Gait) -> dict[str, float]:
    """The phases at which each foot comes down (its heel strike)."""
    return {"left_foot_down": float(np.mod(g.mid_stance - 0.5 * g.duty, 1.0)),
            "right_foot_down": float(np.mod(g.mid_stance + 0.5 - 0.5 * g.duty, 1.0))}
