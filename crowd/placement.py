"""A deterministic stand-in for the crowd AI (issue 4 replaces it): where agents stand and what they play.

Contract: ``Placement(n, seed, bake, roles, strides, upper_body)`` → per frame ``step(dt)`` then
``instances()`` (render input) and ``layers()`` (processor input, (N, 3, 4)).

Agents stand on a jittered grid around the origin, each with a seeded heading, scale, tint and head.
Layer 0 walks, layer 1 runs; their weights follow a per-agent speed mix and both share one phase, so
their feet stay in step. One agent in eight adds an attack on layer 2, on the upper body only where the
skeleton has a spine to mask from. Walkers move forward at stride / duration and wrap around the
area, so feet do not slide (models without stride markers walk in place).
Phases are float64 in [0, 1) on the CPU; only the processor's upload rounds them to float32.
"""

from __future__ import annotations

import math

import numpy as np

from .processor import CLIP, MASK, PHASE, WEIGHT
from .render import Instances

LAYERS = 3
SPACING = 1.6  # metres between grid points
TINTS = np.array([[150, 170, 130], [170, 150, 130], [130, 150, 160], [180, 180, 160], [140, 160, 120], [160, 130, 140]], np.uint8)


class Placement:
    def __init__(self, agents: int, seed: int, bake, roles: dict, strides: dict[str, float], has_mask: bool, head_count: int = 0):
        if agents < 0:
            raise ValueError("agent count must be >= 0")
        self.bake = bake
        self.roles = roles
        self.seed = int(seed)
        self.has_mask = has_mask
        self.head_count = head_count
        self.walk = bake.clip_index(roles["walk"])
        self.run = bake.clip_index(roles["run"])
        self.attack = bake.clip_index(roles["attack"]) if roles.get("attack") else None
        self.walk_info = bake.clips[self.walk]
        self.run_info = bake.clips[self.run]
        self.walk_speed = strides.get(roles["walk"], 0.0) / max(self.walk_info.duration, 1e-6)
        self.run_speed = strides.get(roles["run"], 0.0) / max(self.run_info.duration, 1e-6)
        self.resize(agents)

    def resize(self, agents: int) -> None:
        rng = np.random.default_rng(self.seed)
        n = int(agents)
        self.n = n
        self.origin = np.zeros(3)  # float64 centre of the area the agents wrap around in
        side = max(1, math.ceil(math.sqrt(n)))
        self.half_extent = side * SPACING / 2.0
        ix, iz = np.arange(n) % side, np.arange(n) // side
        self.position = np.zeros((n, 3))
        self.position[:, 0] = (ix - (side - 1) / 2.0) * SPACING + rng.uniform(-0.3, 0.3, n)
        self.position[:, 2] = (iz - (side - 1) / 2.0) * SPACING + rng.uniform(-0.3, 0.3, n)
        self.yaw = rng.uniform(-math.pi, math.pi, n).astype(np.float32)
        self.scale = rng.uniform(0.92, 1.08, n).astype(np.float32)
        tint = TINTS[rng.integers(0, len(TINTS), n)]
        self.tint = np.concatenate([tint, np.full((n, 1), 255, np.uint8)], axis=1)
        self.head = rng.integers(0, max(self.head_count, 1), n)
        self.run_mix = np.clip(rng.uniform(-0.6, 1.0, n), 0.0, 1.0)  # 0: walk, 1: run
        self.phase = rng.uniform(0.0, 1.0, n)  # float64: shared by walk and run
        self.attacking = (np.arange(n) % 8 == 3) & (self.attack is not None)
        self.attack_phase = rng.uniform(0.0, 1.0, n)

    def step(self, dt: float) -> None:
        if not math.isfinite(dt) or dt < 0:
            raise ValueError(f"dt must be finite and >= 0, got {dt!r}")
        dt = min(dt, 0.25)
        duration = (1.0 - self.run_mix) * self.walk_info.duration + self.run_mix * self.run_info.duration
        self.phase = np.mod(self.phase + dt / duration, 1.0)
        speed = (1.0 - self.run_mix) * self.walk_speed + self.run_mix * self.run_speed
        heading = np.stack([np.sin(self.yaw), np.cos(self.yaw)], axis=1).astype(np.float64)
        self.position[:, [0, 2]] += heading * (speed * dt)[:, None]
        # Wrap around the square they started in (a stand-in: the AI steers instead).
        h = self.half_extent + SPACING
        o = self.origin[[0, 2]]
        self.position[:, [0, 2]] = np.mod(self.position[:, [0, 2]] - o + h, 2 * h) - h + o
        if self.attack is not None:
            self.attack_phase = np.mod(self.attack_phase + dt / self.bake.clips[self.attack].duration, 1.0)

    def instances(self) -> Instances:
        variant = {"head": self.head} if self.head_count else {}
        return Instances(self.position, self.yaw, self.scale, self.tint, variant)

    def layers(self) -> np.ndarray:
        out = np.zeros((self.n, LAYERS, 4), np.float32)
        out[..., MASK] = -1.0
        out[:, 0, CLIP] = self.walk
        out[:, 1, CLIP] = self.run
        out[:, 0, PHASE] = self.phase
        out[:, 1, PHASE] = self.phase
        out[:, 0, WEIGHT] = 1.0 - self.run_mix
        out[:, 1, WEIGHT] = self.run_mix
        if self.attack is not None:
            out[:, 2, CLIP] = self.attack
            out[:, 2, PHASE] = self.attack_phase
            out[:, 2, WEIGHT] = np.where(self.attacking, 4.0 if self.has_mask else 0.6, 0.0)  # upper body: 80 % attack
            out[:, 2, MASK] = 0.0 if self.has_mask else -1.0
        return out


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
