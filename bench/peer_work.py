"""The work both sides of ``crowd-bench peers`` do, numpy only: the same agents, headings, phases and
blend weights, frame after frame. The crowd side (bench/peers.py) and the Panda3D side
(bench/peers_panda.py) both import it, so neither imports the other."""

from __future__ import annotations

import math

import numpy as np

from .common import grid_layout

FRAME_DT = 1.0 / 60.0  # simulated seconds per frame, on both sides
WEIGHT_RANGE = (0.3, 0.7)  # the walk's share in the blend modes; the run gets the rest


def agent_layout(n: int, seed: int = 1):
    """Per agent: float64 Y-up positions (n, 3), headings (n,), start phases in [0, 1) (n,) and walk
    weights for the blend (n,); plus the camera (eye, target, far). The same on both sides."""
    pos, eye, target, far = grid_layout(n)
    rng = np.random.default_rng([seed, n])
    yaw = rng.uniform(-math.pi, math.pi, n)
    phase = rng.uniform(0.0, 1.0, n)
    weight = rng.uniform(*WEIGHT_RANGE, n)
    return pos, yaw, phase, weight, (eye, target, far)
