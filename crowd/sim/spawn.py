"""Spawning: new agents anywhere in the world, with their traits (start, resize), or at an edge of it
(respawn); and the random draws keyed by agent and substep that every spawn, respawn and wander target
takes, the same whichever process (or GPU thread: shaders/sim/spawn.comp.glsl) draws an agent's."""

from __future__ import annotations

import math

import numpy as np

from .config import NO_ACTION, WANDER
from .obstacles import CLEARANCE

TINTS = np.array([[150, 170, 130], [170, 150, 130], [130, 150, 160], [180, 180, 160], [140, 160, 120], [160, 130, 140]], np.uint8)
_RESPAWN, _WANDER, _TRAITS, _LOOKS, _ARMS = 1, 2, 3, 4, 5  # what a keyed draw is for (see CrowdAI._draws)
_PLACE = 16  # + the try: a start place's draws
PLACE_TRIES = 33  # a start place in or by an obstacle, or too near the player, is drawn again, up to 32 times
DRAW_BITS = 24  # a draw's bits: what float32 holds exactly, so that the GPU's draws are these numbers
_MASK64 = (1 << 64) - 1


def draw_bound(share: float) -> int:
    """The bound a draw's bits stay below with probability `share`: ``bits < bound`` is ``draw < share``,
    in integers, so that the GPU decides every agent as float64 does."""
    return min(max(math.ceil(float(share) * (1 << DRAW_BITS)), 0), 1 << DRAW_BITS)


def draw_bits(draw: np.ndarray) -> np.ndarray:
    return (draw * (1 << DRAW_BITS)).astype(np.int64)


def draw_pick(draw: np.ndarray, count) -> np.ndarray:
    """floor(draw x count) in integers (exact for any count, as the GPU's umulExtended gives it)."""
    return (draw_bits(draw) * np.asarray(count, np.int64)) >> DRAW_BITS


class SpawnMixin:
    """CrowdAI's part that spawns agents and draws their keyed random numbers."""

    @staticmethod
    def ids(local: np.ndarray) -> np.ndarray:
        """The crowd's own agent numbers (an ``_Agents`` maps its local ones)."""
        return local

    def _draws(self, ids: np.ndarray, purpose: int, count: int) -> np.ndarray:
        """(count, len(ids)) uniform numbers in [0, 1) for agents `ids`, keyed by (seed, agent, substep,
        purpose): the same for an agent whichever process steps it and whatever others draw, which a
        sequential generator cannot give. A counter-based generator: splitmix64's finaliser over the key
        (written here: numpy's Philox draws streams, not one number per key for many keys at once). Each
        is the top DRAW_BITS bits of the 64, which float32 holds exactly: the GPU draws the same numbers."""
        base = (self.seed * 0x9E3779B97F4A7C15 + self.substeps * 0xD1B54A32D192ED03 + purpose * 0xAEF17502108EF2D9) & _MASK64
        key = np.asarray(ids).astype(np.uint64) * np.uint64(0xBF58476D1CE4E5B9) ^ np.uint64(base)
        out = np.empty((count, key.size))
        for row in range(count):
            z = key + np.uint64(((row + 1) * 0x9E3779B97F4A7C15) & _MASK64)
            z ^= z >> np.uint64(30)
            z *= np.uint64(0xBF58476D1CE4E5B9)
            z ^= z >> np.uint64(27)
            z *= np.uint64(0x94D049BB133111EB)
            z ^= z >> np.uint64(31)
            out[row] = (z >> np.uint64(64 - DRAW_BITS)) * (1.0 / (1 << DRAW_BITS))
        return out

    def _unfit_start(self, pos: np.ndarray) -> np.ndarray:
        """Which start places (relative to the origin) lie in or by an obstacle, or within start_clear of the player."""
        off = pos - (self.player - self.origin)
        unfit = off[:, 0] * off[:, 0] + off[:, 1] * off[:, 1] < self.config.start_clear ** 2
        if self.obstacles is not None:  # on the streets
            unfit |= self.obstacles.distance(self.origin[0] + pos[:, 0], self.origin[1] + pos[:, 1]) < CLEARANCE + 0.1
        return unfit

    def _start_places(self, ids: np.ndarray) -> np.ndarray:
        """Start places (relative to the origin) for agents `ids`: each agent's first try that is clear of
        the obstacles and the player (``_unfit_start``), or its last."""
        h = self.half_extent
        pos = np.empty((len(ids), 2))
        todo = np.arange(len(ids))
        for attempt in range(PLACE_TRIES):
            pos[todo] = -h + 2.0 * h * self._draws(ids[todo], _PLACE + attempt, 2).T
            if attempt == PLACE_TRIES - 1:
                break
            todo = todo[self._unfit_start(pos[todo])]
            if not todo.size:
                break
        return pos

    def _spawn(self, a, idx: np.ndarray, anywhere: bool) -> None:
        """New agents `idx` of `a` (the crowd itself, or the agents of one think): anywhere in the world
        (start, resize) or on its edges (respawn). Traits are drawn at first spawn only, so a respawned
        agent keeps its look, speed and weapon."""
        k = len(idx)
        if not k:
            return
        self._respawns += k  # an agent that comes back to life is in no pair of the neighbour list: the step rebuilds it
        a.spawned_step[idx] = self.steps
        cfg, h = self.config, self.half_extent
        if anywhere:
            ids = a.ids(np.asarray(idx))
            self.start_player = self.player.copy()  # (the start clearance's centre: the GPU's spawn takes it too)
            pos = self._start_places(ids)
            traits, looks, arms = self._draws(ids, _TRAITS, 4), self._draws(ids, _LOOKS, 4), self._draws(ids, _ARMS, 3)
            yaw = -math.pi + 2.0 * math.pi * traits[0]
            a.phase[idx] = traits[1]
            a.speed_factor[idx] = cfg.speed_min + (cfg.speed_max - cfg.speed_min) * traits[2]
            a.reaction[idx] = cfg.reaction_min + (cfg.reaction_max - cfg.reaction_min) * traits[3]
            a.runner[idx] = draw_bits(looks[0]) < draw_bound(cfg.runner_share)
            a.scale[idx] = 0.92 + 0.16 * looks[1]
            a.tint[idx, :3] = TINTS[draw_pick(looks[2], len(TINTS))]
            a.tint[idx, 3] = 255
            # Each agent's traits from its own character: its head choices, weapons and speeds.
            kind = a.kind[idx] if len(self.motions) > 1 else 0
            heads = np.array([max(m.head_count, 1) for m in self.motions])[kind]
            weapons = np.array([m.weapon_count for m in self.motions])[kind]
            a.head[idx] = draw_pick(looks[3], heads)
            armed = (draw_bits(arms[0]) < draw_bound(cfg.armed_share)) & (weapons > 0)
            a.weapon[idx] = np.where(armed, np.array([m.weapon_first for m in self.motions])[kind] + draw_pick(arms[1], np.maximum(weapons, 1)), -1)
            a.walk_top[idx] = self._walk_speed[kind] * a.speed_factor[idx]
            a.chase_top[idx] = np.where(a.runner[idx], self._run_speed[kind], self._walk_speed[kind]) * a.speed_factor[idx]
            pause = 2.0 * arms[2]
        else:  # while stepping: draws keyed by agent and substep, so any split of the crowd gives the same ones
            draw = self._draws(a.ids(idx), _RESPAWN, 3)
            side = np.minimum((draw[0] * 4.0).astype(np.int64), 3)
            along = -h + 2.0 * h * draw[1]
            edge = np.where(side % 2 == 0, -1.0, 1.0) * (h - 0.5)
            pos = np.where((side < 2)[:, None], np.stack([edge, along], axis=1), np.stack([along, edge], axis=1))
            yaw = np.arctan2(-pos[:, 0], -pos[:, 1])  # face the middle
            pause = 2.0 * draw[2]
        a.x[idx] = self.origin[0] + pos[:, 0]
        a.z[idx] = self.origin[1] + pos[:, 1]
        if self.obstacles is not None:  # (an edge of the world that runs through a building)
            a.x[idx], a.z[idx] = self.keep_out(a.x[idx], a.z[idx])
        a.hx[idx], a.hz[idx] = np.sin(yaw), np.cos(yaw)
        a.vx[idx] = a.vz[idx] = 0.0
        a.tx[idx], a.tz[idx] = a.x[idx], a.z[idx]
        a.state[idx] = WANDER
        a.state_time[idx] = 0.0
        a.aware[idx] = 0.0
        a.pause[idx] = pause
        a.health[idx] = int(cfg.health)
        a.action[idx] = NO_ACTION
        a.action_time[idx] = 0.0
        a.cooldown[idx] = 0.0
