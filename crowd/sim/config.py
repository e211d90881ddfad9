"""The crowd AI's settings (``AIConfig``, declared once in crowd.settings' ``ai`` group), its error, and
the codes every part of it shares: the agents' states, their actions and the layers they are drawn with."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import CrowdError
from ..frame import MAX_LAYERS
from ..settings import group

LAYERS = MAX_LAYERS
# States (int8).
WANDER, CHASE, ATTACK, HIT, DYING, DEAD = range(6)
STATE_NAMES = ("wander", "chase", "attack", "hit", "dying", "dead")
# Actions (int8): which clip layer 3 plays.
NO_ACTION, ACT_ATTACK, ACT_HIT, ACT_DEATH = range(4)
ACTION_ROLES = (None, "attack", "hit", "death")
# A zombie's blow lands this far through its attack clip, on a player then within attack_reach times
# BLOW_REACH (the swing carries the arm a little past where it began): a player who moves away dodges it.
ATTACK_IMPACT = 0.5
BLOW_REACH = 1.25


class AIError(CrowdError, ValueError):
    """Bad AI input; the message is one line."""


# A step up to this share longer than the substep takes one substep: a 60 Hz window's frames (16.7 ms give
# or take the display's jitter) took one substep and then two by turns, twice the AI's work on every other frame.
SUBSTEP_SLACK = 0.05
_AI = {name: setting.default for name, setting in group("ai").items()}


@dataclass(frozen=True)
class AIConfig:
    """The AI's settings. Each one's default, bounds and help are declared once, in the ``ai`` group of
    crowd.settings; a test checks that these fields are that group."""

    substep: float = _AI['substep']
    max_dt: float = _AI['max_dt']
    notice_radius: float = _AI['notice_radius']
    forget_radius: float = _AI['forget_radius']
    alert_rate: float = _AI['alert_rate']
    start_clear: float = _AI['start_clear']
    reaction_min: float = _AI['reaction_min']
    reaction_max: float = _AI['reaction_max']
    attack_reach: float = _AI['attack_reach']
    attack_cooldown: float = _AI['attack_cooldown']
    separation_radius: float = _AI['separation_radius']
    separation_stiffness: float = _AI['separation_stiffness']
    max_accel: float = _AI['max_accel']
    turn_rate: float = _AI['turn_rate']
    plant_feet: bool = _AI['plant_feet']
    arrive_distance: float = _AI['arrive_distance']
    wander_radius: float = _AI['wander_radius']
    wander_speed: float = _AI['wander_speed']
    speed_min: float = _AI['speed_min']
    speed_max: float = _AI['speed_max']
    runner_share: float = _AI['runner_share']
    armed_share: float = _AI['armed_share']
    crossfade: float = _AI['crossfade']
    corpse_time: float = _AI['corpse_time']
    health: int = _AI['health']
    area_per_agent: float = _AI['area_per_agent']
    min_half_extent: float = _AI['min_half_extent']
    half_extent: float = _AI['half_extent']
    think_every: int = _AI['think_every']
    think_radius: float = _AI['think_radius']
    think_from: int = _AI['think_from']
    workers: int = _AI['workers']

    def substeps_for(self, dt: float) -> int:
        """Equal substeps a step of `dt` seconds (clamped to max_dt already) is made of: as few as keep each
        at most `substep`, give or take SUBSTEP_SLACK of it (none for dt = 0)."""
        return max(1, math.ceil(dt / self.substep - SUBSTEP_SLACK)) if dt > 0.0 else 0

    def alert(self, time: float) -> float:
        """Metres the notice and forget radii have grown `time` seconds into a round (alert_rate), at most
        to think_radius: a zombie that may notice the player still thinks every substep."""
        return min(self.alert_rate * max(float(time), 0.0), max(self.think_radius - self.notice_radius, 0.0))

    def validate(self) -> "AIConfig":
        for name, setting in group("ai").items():
            setting.check(getattr(self, name), AIError)
        # Relations between settings (each one's own bounds are the schema's).
        if self.reaction_max < self.reaction_min or self.speed_max < self.speed_min:
            raise AIError("AI ranges need min <= max (reaction, speed)")
        if self.forget_radius < self.notice_radius:
            raise AIError("AI forget_radius must be >= notice_radius")
        if self.substep > self.max_dt:
            raise AIError("AI needs substep <= max_dt")
        if self.think_every > 1 and self.think_radius < self.notice_radius:  # the budget may be used at some crowd size
            raise AIError("AI think_radius must be >= notice_radius (a zombie that may notice the player thinks every substep)")
        return self

    def half_extent_for(self, agents: int, free_share: float = 1.0) -> float:
        """The world's half width for a crowd: area_per_agent of open ground each, on a ground of which
        `free_share` is open (the rest buildings and cars), and the start_clear disc besides."""
        if self.half_extent > 0:
            return float(self.half_extent)
        clear = math.pi * self.start_clear ** 2 if agents else 0.0  # the disc kept free at the start: the horde keeps its density around it
        return max(self.min_half_extent, 0.5 * math.sqrt(agents * self.area_per_agent / free_share + clear))
