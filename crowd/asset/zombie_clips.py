"""The zombie's clips, authored as functions of phase: its gaits, each clip's pose over its cycle, the
specs build_clips keys them by (crowd.asset.clip_keys), and the snarl each clip keys."""

from __future__ import annotations

import numpy as np

from .planted_feet import _Gait, _foot_markers, _planted, _standing
from .pose_angles import TAU, _bump, _keyed, _neutral

SHAMBLE_GAIT = _Gait(stride=0.9, duty=0.6, lift=0.2, mid_stance=0.3, height=(0.09, 0.07), toe_down=(0.25, 0.2),
                     toe_out=(0.1, 0.25))
RUN_GAIT = _Gait(stride=2.3, duty=0.3, lift=0.08, mid_stance=0.3, height=(0.22, 0.22), toe_down=(0.5, 0.5),
                 toe_out=(0.08, 0.08))


def _shamble(p):
    a = _neutral(p.shape[0])
    c, s = np.cos(TAU * p), np.sin(TAU * p)
    a["hips_x"] = 0.035 * s
    a["hips_pitch"] = 0.12 + 0.02 * np.cos(2 * TAU * p)
    a["hips_yaw"] = 0.14 * c
    a["hips_roll"] = -0.07 * s
    a["spine_pitch"] = 0.12
    a["chest_pitch"] = 0.22 + 0.03 * np.cos(2 * TAU * p)
    a["chest_yaw"] = -0.12 * c
    a["chest_roll"] = 0.08 + 0.04 * s  # lopsided
    a["neck_pitch"] = -0.25
    a["head_pitch"] = -0.05 + 0.06 * np.cos(2 * TAU * p + 0.6)
    a["head_roll"] = 0.3 + 0.05 * s
    a["jaw"] = 0.18 + 0.08 * np.sin(2 * TAU * p)
    # The left arm reaches forward, the right one hangs and swings: zombies are not symmetric.
    a["arm_down_l"] = -0.35 + 0.06 * np.sin(2 * TAU * p)  # raised against the forward lean: level and reaching
    a["arm_fwd_l"] = 1.3 + 0.05 * c
    a["arm_twist_l"] = -0.6
    a["elbow_l"] = 0.2 + 0.05 * s
    a["wrist_l"] = 0.5
    a["arm_down_r"] = 0.35 + 0.1 * c
    a["arm_fwd_r"] = 1.0 - 0.2 * c
    a["arm_twist_r"] = -0.4
    a["elbow_r"] = 0.4 + 0.1 * s
    a["wrist_r"] = 0.35
    # The legs are solved for SHAMBLE_GAIT's foot paths: the left one steps high, the right one limps,
    # low and toes down. The hips sit low enough for the legs to reach the ends of the stride.
    a["hips_y"] = -0.08 + 0.03 * np.cos(2 * TAU * (p - SHAMBLE_GAIT.mid_stance))  # highest over a planted foot
    return _planted(p, a, SHAMBLE_GAIT)


def _run(p):
    a = _neutral(p.shape[0])
    p_strike = p - RUN_GAIT.mid_stance + 0.5 * RUN_GAIT.duty  # phase since the left heel strike
    c, s = np.cos(TAU * p_strike), np.sin(TAU * p_strike)
    a["hips_x"] = 0.025 * s
    a["hips_pitch"] = 0.25
    a["hips_yaw"] = 0.2 * c
    a["spine_pitch"] = 0.15
    a["chest_pitch"] = 0.35
    a["chest_yaw"] = -0.25 * c
    a["neck_pitch"] = -0.45
    a["head_pitch"] = -0.1 + 0.08 * np.cos(2 * TAU * p)
    a["head_roll"] = 0.15 * s
    a["jaw"] = 0.45
    # Arms flail forward, clawing.
    a["arm_down_l"] = 0.55 - 0.35 * c
    a["arm_fwd_l"] = 1.0 - 0.5 * c
    a["elbow_l"] = 0.9 + 0.4 * c
    a["wrist_l"] = 0.4
    a["arm_down_r"] = 0.55 + 0.35 * c
    a["arm_fwd_r"] = 1.0 + 0.5 * c
    a["elbow_r"] = 0.9 - 0.4 * c
    a["wrist_r"] = 0.4
    a["hips_y"] = -0.15 + 0.03 * np.cos(2 * TAU * (p - RUN_GAIT.mid_stance))  # _planted lowers it where the stride needs
    return _planted(p, a, RUN_GAIT)


def _idle(p):
    a = _neutral(p.shape[0])
    s = np.sin(TAU * p)
    a["hips_x"] = 0.02 * s
    a["hips_roll"] = -0.04 * s
    a["spine_pitch"] = 0.1
    a["chest_pitch"] = 0.18 + 0.03 * np.sin(2 * TAU * p)  # laboured breathing
    a["chest_roll"] = 0.06
    a["neck_pitch"] = -0.05
    a["head_pitch"] = 0.25 + 0.1 * np.sin(TAU * p + 1.0)
    a["head_roll"] = 0.35 + 0.15 * s
    a["head_yaw"] = 0.15 * np.sin(TAU * p + 0.5)
    a["jaw"] = 0.25 + 0.15 * np.sin(3 * TAU * p)
    for side, ph in (("l", 0.0), ("r", 0.9)):
        a[f"arm_down_{side}"] = 1.3 + 0.05 * np.sin(TAU * p + ph)
        a[f"arm_fwd_{side}"] = 0.25 + 0.08 * np.sin(TAU * p + ph)
        a[f"elbow_{side}"] = 0.3 + 0.05 * np.sin(TAU * p + ph + 0.5)
        a[f"wrist_{side}"] = 0.3
    a["hips_y"] = -0.03  # knees a little bent over the planted feet
    return _standing(p, a)


def _attack(p):
    """Overhead swing with the right (weapon) hand: wind up, strike down, recover."""
    a = _idle(np.zeros_like(p))
    keys = [
        (0.0, {}),
        (0.3, dict(arm_down_r=-1.4, arm_fwd_r=0.7, arm_twist_r=-0.6, elbow_r=1.1, wrist_r=-0.3, chest_yaw=0.45, chest_pitch=-0.05,
                   spine_yaw=0.2, head_pitch=0.0, jaw=0.6, thigh_flex_r=-0.15, knee_r=0.3, thigh_flex_l=0.25)),
        (0.48, dict(arm_down_r=0.9, arm_fwd_r=1.5, arm_twist_r=0.2, elbow_r=0.15, wrist_r=0.3, chest_yaw=-0.5, chest_pitch=0.45,
                    spine_yaw=-0.2, spine_pitch=0.2, head_pitch=0.2, jaw=0.7, arm_down_l=1.0, arm_fwd_l=0.2, thigh_flex_l=0.45, knee_l=0.35,
                    hips_pitch=0.15)),
        (0.62, dict(arm_down_r=1.15, arm_fwd_r=1.0, elbow_r=0.3, chest_yaw=-0.35, chest_pitch=0.38)),
        (1.0, {}),
    ]
    # The last key returns to the idle pose at p = 0 so that cross-fades in and out are clean.
    return _keyed(p, keys, a)


def _hit(p):
    a = _idle(np.zeros_like(p))
    keys = [
        (0.0, {}),
        (0.18, dict(chest_pitch=-0.3, spine_pitch=-0.15, head_pitch=-0.55, head_roll=0.6, hips_z=-0.06, hips_pitch=-0.1, jaw=0.6,
                    arm_down_l=0.4, arm_fwd_l=-0.3, elbow_l=0.6, arm_down_r=0.5, arm_fwd_r=-0.2, elbow_r=0.7, knee_l=0.35, knee_r=0.3,
                    thigh_flex_l=0.25)),
        (0.45, dict(chest_pitch=0.3, head_pitch=0.35, head_roll=0.2, hips_z=-0.04, arm_down_l=1.1, arm_down_r=1.2, elbow_l=0.4)),
        (1.0, {}),
    ]
    return _keyed(p, keys, a)


def _death(p):
    """Knees buckle, the body topples backwards and lies still on its back."""
    a = _idle(np.zeros_like(p))
    keys = [
        (0.0, {}),
        (0.15, dict(chest_pitch=-0.35, head_pitch=-0.6, head_roll=0.5, hips_z=-0.05, jaw=0.8, arm_down_l=0.5, arm_down_r=0.6,
                    arm_fwd_l=-0.2, arm_fwd_r=-0.1, elbow_l=0.8, elbow_r=0.6)),
        (0.35, dict(hips_y=-0.38, hips_pitch=0.15, chest_pitch=0.25, head_pitch=0.5, knee_l=1.9, knee_r=1.7, thigh_flex_l=1.1,
                    thigh_flex_r=1.0, ankle_l=-0.55, ankle_r=-0.5, arm_down_l=1.2, arm_down_r=1.3, arm_fwd_l=0.3, arm_fwd_r=0.2)),
        (0.62, dict(hips_y=-0.84, hips_z=-0.55, hips_pitch=-1.5, chest_pitch=-0.05, spine_pitch=0.0, head_pitch=-0.3, head_roll=0.6,
                    knee_l=0.5, knee_r=0.7, thigh_flex_l=0.4, thigh_flex_r=0.6, ankle_l=0.3, ankle_r=0.4, arm_down_l=0.1,
                    arm_down_r=-0.1, arm_fwd_l=-0.6, arm_fwd_r=-0.5, elbow_l=0.3, elbow_r=0.5, jaw=0.5)),
        (0.72, dict(hips_y=-0.80, head_pitch=-0.2)),
        (0.85, dict(hips_y=-0.85, head_pitch=-0.35, knee_l=0.35, knee_r=0.5, thigh_flex_l=0.3, thigh_flex_r=0.45, ankle_l=0.5,
                    ankle_r=0.6, arm_down_l=0.05, arm_down_r=-0.15, wrist_l=0.0, wrist_r=0.0)),
        (1.0, dict()),
    ]
    return _keyed(p, keys, a)


def _crawl(p):
    """Legs useless, pulling itself along with alternating arms (left hand plants at p = 0)."""
    a = _neutral(p.shape[0])
    c, s = np.cos(TAU * p), np.sin(TAU * p)
    a["hips_y"] = -0.73 + 0.015 * np.cos(2 * TAU * p)
    a["hips_pitch"] = 1.42
    a["hips_roll"] = 0.08 * s
    a["spine_pitch"] = -0.1 - 0.05 * np.cos(2 * TAU * p)
    a["chest_pitch"] = -0.2
    a["chest_roll"] = -0.12 * s
    a["chest_yaw"] = 0.1 * c
    a["neck_pitch"] = -0.5
    a["head_pitch"] = -0.35
    a["head_roll"] = 0.2
    a["jaw"] = 0.4 + 0.2 * np.sin(2 * TAU * p)
    for side, ph in (("l", 0.0), ("r", 0.5)):
        cc = np.cos(TAU * (p - ph))
        reach = 0.5 + 0.5 * cc  # 1 when the hand plants far forward
        a[f"arm_down_{side}"] = 0.6 - 1.9 * reach
        a[f"arm_fwd_{side}"] = 0.9 + 0.2 * np.sin(TAU * (p - ph))
        a[f"elbow_{side}"] = 0.25 + 1.0 * (1.0 - reach)
        a[f"wrist_{side}"] = 0.2
        a[f"thigh_flex_{side}"] = -0.1 + 0.08 * cc
        a[f"thigh_abd_{side}"] = 0.12
        a[f"knee_{side}"] = 0.25 + 0.15 * _bump(p, ph + 0.5, 0.15)
        a[f"ankle_{side}"] = 0.9
    return a


# name, authoring function, duration (s), loop, phase markers, stride (m per cycle), keep feet grounded
CLIP_SPECS = [
    ("idle", _idle, 3.0, True, {}, None, False),
    ("shamble", _shamble, 1.6, True, _foot_markers(SHAMBLE_GAIT), SHAMBLE_GAIT.stride, False),
    ("run", _run, 0.7, True, _foot_markers(RUN_GAIT), RUN_GAIT.stride, False),
    ("attack", _attack, 1.2, False, {"impact": 0.48}, None, True),
    ("hit", _hit, 0.6, False, {}, None, True),
    ("death", _death, 2.2, False, {}, None, False),
    ("crawl", _crawl, 2.4, True, {"left_hand_down": 0.0, "right_hand_down": 0.5}, 0.55, False),
]


# Each clip's snarl, by phase: slack while wandering, bared while chasing, widest at an attack's strike.
# The AI cross-fades the clips (crowd.sim.ai), and their snarls with them: that is how it sets the face.
SNARL = {
    "idle": lambda p: 0.1 + 0.05 * np.sin(TAU * p),
    "shamble": lambda p: 0.2 + 0.05 * np.sin(2 * TAU * p),
    "run": lambda p: 0.85 + 0.15 * np.sin(2 * TAU * p),
    "attack": lambda p: np.interp(p, [0.0, 0.3, 0.48, 0.8, 1.0], [0.4, 0.9, 1.0, 0.6, 0.4]),
    "hit": lambda p: np.interp(p, [0.0, 0.2, 1.0], [0.3, 0.8, 0.4]),
    "death": lambda p: np.interp(p, [0.0, 0.3, 1.0], [0.6, 0.8, 0.0]),
    "crawl": lambda p: 0.5 + 0.1 * np.sin(TAU * p),
}
