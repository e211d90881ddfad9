"""Think budget (settings think_every, think_radius, think_from): in a big crowd, zombies far from the
player and the camera (``focus``) that wander or lie dead think every think_every substeps, a block
of consecutive agents at a time, and coast at their velocity and phase rate in between; everyone
else, and every action, is stepped exactly as without it (``_budgeted_think``).
"""

from __future__ import annotations

import math

import numpy as np

from .config import DEAD, WANDER
from .locomotion import advance_phase
from .think import _Agents, _rotate_toward


class ThinkBudgetMixin:
    """CrowdAI's part that decides who thinks every substep and coasts the rest between thinks."""

    def exact_count(self) -> int:
        """Zombies that think every substep: all of them without the budget."""
        return int(np.count_nonzero(self._exact)) if self.budgeted() else self.n

    def budgeted(self) -> bool:
        """Whether the think budget is in use: think_every above 1, for a crowd of think_from or more."""
        return self.config.think_every > 1 and self.n >= self.config.think_from

    def _budgeted_think(self, lo: int, hi: int, h: float, b0: int, b1: int, block: slice) -> dict:
        """The think budget's think phase (crowd.settings: think_every, think_radius): agents that must
        be exact (near the player or a focus point, or doing anything but wandering and lying dead)
        think every substep; the rest are cut into think_every blocks of consecutive agents, and one
        block (agents b0..b1) thinks per substep, over the time since it last did. Between thinks an
        agent keeps its velocity and phase rate: its position and phase move every substep (no
        stutter), it goes on turning toward the heading its think chose, and its timers, steering and
        animation weights catch up when it thinks. An exact agent is stepped exactly as with the budget
        off: it takes no time from the budget, and its substep is the same arithmetic.

        Who does what, so that the processes share the block's work evenly and never touch one agent
        at once: each thinks its slice `block` of the block (through views) and the block's exact
        agents in it, the exact agents of its range lo..hi outside the block (gathered and scattered
        back), and coasts the rest of its range. Returns what the finish phase needs."""
        in_block = self._exact[block]  # exact agents inside the block think with the exact ones, not here
        think_h = np.where(in_block, 0.0, self._pending[block] + h)  # time since the block's agents last thought
        move_h = np.where(in_block, 0.0, h)  # this substep's motion (the rest was moved between thinks)
        self._pending[block] = 0.0

        # The block's slice thinks through views, its exact agents too (with no time: they think below);
        # what its first half changes of them (a transition seen from where they stand after moving, a
        # timer) is put back, so they start their exact substep from where the last one left them.
        inside = block.start + np.flatnonzero(in_block)
        restore = _Agents(self, inside)
        group = _Agents(self, block)
        near_block = self._think_a(group, think_h, move_h)
        group.commit()
        restore.commit()
        thinking = self._exact[lo:hi].copy()  # the range's exact agents, and below its part of the block
        blocked = slice(min(max(b0, lo), hi) - lo, max(min(b1, hi), lo) - lo)
        outside = thinking.copy()
        outside[blocked] = False
        exact = np.concatenate([lo + np.flatnonzero(outside), inside])
        group = _Agents(self, exact)
        near_exact = self._think_a(group, h, h)
        group.commit()

        # The rest of the range moves on at its velocity and phase rate (and is separated with everyone).
        # Only those agents are written (`where=`): the range's part of the block and its exact agents
        # there belong to the processes thinking them, which write them at the same time.
        thinking[blocked] = True
        coasting = ~thinking
        for position, velocity in ((self.x[lo:hi], self.vx[lo:hi]), (self.z[lo:hi], self.vz[lo:hi])):
            np.add(position, velocity * h, out=position, where=coasting)
        advance_phase(self.phase[lo:hi], self.phase_rate[lo:hi] * h, where=coasting)
        pending = self._pending[lo:hi]
        np.add(pending, h, out=pending, where=coasting)
        turning = lo + np.flatnonzero(self._coast_turn[lo:hi] & coasting)
        if turning.size:
            self._coast_turns(turning, self.config.turn_rate * h)
        return dict(exact=exact, block=block, think_h=think_h, move_h=move_h, near_block=near_block, near_exact=near_exact,
                    coasting=coasting)

    def _must_be_exact(self, a) -> np.ndarray:
        """Agents of `a` that think every substep: all but the wandering and the dead, and everyone
        within think_radius of the player or of a focus point (the camera)."""
        r2 = self.config.think_radius ** 2
        exact = (a.state != WANDER) & (a.state != DEAD)
        for fx, fz in (self.player, *self.focus):
            dx, dz = a.x - float(fx), a.z - float(fz)
            exact |= dx * dx + dz * dz < r2
        return exact

    def _coast_turns(self, coasting: np.ndarray, step: float) -> None:
        """Between thinks: the budgeted agents still turning (`coasting`, indices) turn toward the goal
        their last think set, by `step` as an exact agent turns each substep, snapping when within it.
        They turn about their origin: a coasting agent is far from the player and the camera, where a
        foot's pivot is not seen, and pivoting them cost 1 ms a step at 100,000 agents on one core."""
        hx, hz, ux, uz = self.hx[coasting], self.hz[coasting], self._goal_x[coasting], self._goal_z[coasting]
        near = hx * ux + hz * uz >= math.cos(step)
        rx, rz = _rotate_toward(hx, hz, ux, uz, step)
        self.hx[coasting] = np.where(near, ux, rx)
        self.hz[coasting] = np.where(near, uz, rz)
        self._coast_turn[coasting[near]] = False
