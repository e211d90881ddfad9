"""The rows of agents the stages draw each frame, the crowd's and then the survivor's, and what each row
needs beyond the AI's own arrays: its instance, the weapon it holds (and, where impostors hold weapons,
its choice there), the weapons the CPU places, and the foot lock's ground steps.

Each is one pass over spans of the agents side by side (crowd.spans), without gathers: at a million
agents a gather or a fancy-indexed pass cost tens of milliseconds a frame (docs/BENCHMARKS.md, "The CPU
side of the frame").
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .asset.model import Character, cast_weapons
from .draw.impostors import HELD_GROUP
from .draw.render import CrowdRenderer
from .frame import Instances, cast_firsts
from .sim.ai import CrowdAI
from .sim.config import DYING
from .sim.player import Survivor
from .spans import over_spans


def drawn_instances(ai: CrowdAI, survivor: Survivor | None, characters: list[Character], group_names: list[str],
                    counts: tuple[int, ...]) -> Instances:
    """What the renderer draws this frame: the crowd's instances, and the survivor's after them; each
    row's choice in the held-weapon group where the renderer draws one (`group_names`)."""
    s = survivor
    crowd = ai.instances(extra=0 if s is None else 1)
    variant = dict(crowd.variant)
    if HELD_GROUP in group_names:
        variant[HELD_GROUP] = held_choices(ai, characters, len(crowd))
    if s is None:
        return dataclasses.replace(crowd, variant=variant)
    n = ai.n
    crowd.position[n] = (s.position[0], 0.0, s.position[1])
    crowd.yaw[n], crowd.scale[n], crowd.tint[n] = np.float32(s.yaw), np.float32(1.0), 255
    if "head" in group_names and "head" not in variant:
        variant["head"] = np.zeros(n + 1, np.int32)
    return Instances(crowd.position, crowd.yaw, crowd.scale, crowd.tint, variant, counts)


def held_choices(ai: CrowdAI, characters: list[Character], rows: int) -> np.ndarray:
    """Each drawn agent's choice where impostors hold weapons (crowd.draw.impostors.HELD_GROUP): 0 unarmed
    (and the survivor's row), else 1 + its weapon among its character's props. Per character block."""
    first, _ = cast_weapons(characters)
    firsts = cast_firsts(ai.cast)
    held = np.zeros(rows, np.int32)

    def choose(lo: int, hi: int) -> None:
        for k in range(len(firsts) - 1):
            a, b = max(lo, int(firsts[k])), min(hi, int(firsts[k + 1]))
            if a < b:  # weapon - the character's first + 1 where armed (a living agent with a weapon), else 0
                armed = (ai.weapon[a:b] >= 0) & (ai.state[a:b] < DYING)
                np.add(ai.weapon[a:b], 1 - int(first[k]), out=held[a:b], casting="unsafe")
                np.multiply(held[a:b], armed, out=held[a:b], casting="unsafe")

    over_spans(choose, ai.n)
    return held


def weapon_of_agent(ai: CrowdAI, characters: list[Character], survivor: Survivor | None) -> np.ndarray:
    """Each drawn agent's weapon (-1: none): the crowd's, then the survivor's (its character's first)."""
    if survivor is None:
        return ai.weapon
    first, _ = cast_weapons(characters)
    return np.append(ai.weapon, first[-1] if characters[-1].armed else -1).astype(ai.weapon.dtype)


def placed_weapons(ai: CrowdAI, renderer: CrowdRenderer, eye, weapon_of_agent: np.ndarray, instances: Instances,
                   survivor_kind: int) -> np.ndarray:
    """The agents whose weapons the CPU places this frame: those holding one (a living armed zombie, the
    survivor where it has one, character `survivor_kind`) that may be drawn as meshes, which leaves out
    the agents of characters with impostors past the impostor distance and its fade band (with a
    bounding radius to spare, as the cull measures from the sphere's centre): the CPU's work on weapons
    then grows with the agents drawn as meshes, not with the crowd. No gathers."""
    n = ai.n
    impostor_lods = np.asarray(renderer.impostor_lods)
    impostors = bool(np.any(impostor_lods >= 0))
    reach = renderer.impostor_distance + renderer.lod_fade + float(renderer.bounds[:, 3].max()) * 2.0
    eye = np.asarray(eye, np.float64)

    def pick(lo: int, hi: int) -> np.ndarray:
        keep = weapon_of_agent[lo:hi] >= 0
        top = min(hi, n)  # (the crowd's rows; the survivor's after them)
        if lo < top:
            keep[:top - lo] &= ai.state[lo:top] < DYING
        if impostors:
            d2 = np.zeros(hi - lo)
            for c in range(3):
                axis = instances.position[lo:hi, c] - eye[c]
                d2 += axis * axis
            kind = np.full(hi - lo, survivor_kind, np.int64)
            kind[:max(top - lo, 0)] = ai.kind[lo:top]
            keep &= (d2 <= reach * reach) | (impostor_lods[kind] < 0)
        return np.flatnonzero(keep) + lo

    return np.concatenate(over_spans(pick, len(weapon_of_agent)))


class FootLockSteps:
    """The foot lock's input: each row's ground step since the last run (float64, so a world far from the
    origin loses nothing to float32) and its front times its scale, written into arrays kept between
    frames. A new agent, or the first run after `reset` (a new processor, a new crowd), steps 0; a
    respawn steps as far as it was moved, which the lock reads as a teleport. The survivor's row
    follows the crowd's."""

    def __init__(self):
        self.ground: np.ndarray | None = None  # each row's ground point (2, rows: x, z) at the last run
        self.motion = np.empty((0, 4), np.float32)

    def reset(self) -> None:
        """Forget where everyone stood: every row steps 0 at the next run."""
        self.ground = None

    def since_last_run(self, ai: CrowdAI, survivor: Survivor | None, rows: int) -> np.ndarray:
        """(rows, 4) float32: each row's ground step (x, z) and its front (x, z) times its scale."""
        n = ai.n
        last = self.ground
        if last is None or last.shape[1] != rows:
            fresh = np.zeros((2, rows))
            fresh[0, :n], fresh[1, :n] = ai.x, ai.z
            if survivor is not None:
                fresh[:, n] = survivor.position
            if last is not None:
                keep = min(n, last.shape[1])
                fresh[:, :keep] = last[:, :keep]
            last = self.ground = fresh
            self.motion = np.empty((rows, 4), np.float32)
        motion = self.motion

        def step(lo: int, hi: int) -> None:  # over spans of agents side by side (crowd.spans)
            np.subtract(ai.x[lo:hi], last[0, lo:hi], out=motion[lo:hi, 0], casting="same_kind")
            np.subtract(ai.z[lo:hi], last[1, lo:hi], out=motion[lo:hi, 1], casting="same_kind")
            np.multiply(ai.hx[lo:hi], ai.scale[lo:hi], out=motion[lo:hi, 2], casting="same_kind")
            np.multiply(ai.hz[lo:hi], ai.scale[lo:hi], out=motion[lo:hi, 3], casting="same_kind")
            last[0, lo:hi] = ai.x[lo:hi]
            last[1, lo:hi] = ai.z[lo:hi]

        over_spans(step, n)
        if survivor is not None:
            motion[n] = (*(survivor.position - last[:, n]), *survivor.heading)
            last[:, n] = survivor.position
        return motion
