"""The player's character: the survivor, moved by the player (or the headless script), animated from its
speed and actions, hurt by the zombies that reach it. Plain numpy, like the AI; the pipeline draws it as
one more character of the cast, in the palette row after the crowd's.

Contract: ``Survivor(motion, position)``; each frame ``command(move, face)`` (or ``walk_to(point)``) and
``strike()`` as the input says, ``step(dt)`` (True when a strike lands: the caller hits the zombie in
front), ``hurt(blows)`` with the zombies' blows since the last frame, then ``write_layers(out)`` and the
transform (``position``, ``yaw``) for the processor and the renderer.

Movement is relative to where the survivor faces: it runs forward at the run clip's own speed (its feet
keep pace), backs off at half that with the run played backward, and side-steps at STRAFE_SPEED with the
strafe clips, between which a move's direction blends. It faces `face` when one is given (the follow
camera's forward, so the player strafes around a zombie it watches), else where it moves. One phase is
shared by the locomotion clips, advanced by the speed along the clip that carries the most weight over
that clip's stride, as the crowd's is.

A round: health starts at HEALTH; each zombie blow takes BLOW_DAMAGE and plays the flinch. At 0 the round
is over (``down``); ``new_round()`` starts the next one, keeping the best time survived so far and the
ended round's record in ``history`` (crowd.sim.rounds plays them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import CrowdError
from ..frame import CLIP, MASK, PHASE, WEIGHT
from .locomotion import advance_phase
from .outputs import MAX_ACTION_WEIGHT

ROLES = ("idle", "run", "strafe_left", "strafe_right", "strike", "hit")
HEALTH = 100
BLOW_DAMAGE = 10  # a zombie's landed attack
# Health comes back at REGEN_RATE a second once no blow has landed for REGEN_DELAY seconds: a player who
# gets clear of the horde recovers, one who stands in it does not.
REGEN_DELAY = 4.0
REGEN_RATE = 5.0
STRIKE_REACH = 2.0  # metres: the bat reaches a zombie this close in front
STRAFE_SPEED = 1.2  # m/s side-stepping (the strafe clips played faster than their own 0.75 m/s)
BACK_SHARE = 0.5  # backing off, as a share of the run speed
ACCEL = 14.0  # m/s^2 toward the commanded velocity
TURN_RATE = 9.0  # rad/s
MOVING = 0.4  # m/s at which locomotion has fully replaced idle
CROSSFADE = 0.12  # seconds an action fades in and out
NONE, STRIKE, HIT = 0, 1, 2


class PlayerError(CrowdError, ValueError):
    """Bad input for the survivor; the message is one line."""


@dataclass(frozen=True)
class SurvivorMotion:
    """What the survivor's controller needs of its baked clips."""

    clip: dict  # role -> clip index in its bake
    duration: dict  # role -> seconds (at its playback speed)
    run_stride: float  # metres a run cycle covers
    strafe_stride: float  # metres a strafe cycle covers, sideways
    impact: float  # phase of the strike at which the bat lands
    upper_body_mask: int  # mask row of the upper body, or -1

    @property
    def run_speed(self) -> float:
        return self.run_stride / self.duration["run"]


def survivor_motion(character, bake, upper_body_mask: int = 0, clip_speed: dict | None = None) -> SurvivorMotion:
    """The SurvivorMotion of a character whose clips are named as ROLES (the built-in survivor's)."""
    missing = [r for r in ROLES if r not in {c.name for c in bake.clips}]
    if missing:
        raise PlayerError(f"the survivor needs clips named {', '.join(ROLES)}; {character.name!r} lacks {', '.join(missing)}")
    speed = clip_speed or {}
    clip = {r: bake.clip_index(r) for r in ROLES}
    duration = {r: max(bake.clips[clip[r]].duration / float(speed.get(r, 1.0)), 1e-3) for r in ROLES}
    return SurvivorMotion(clip, duration, float(character.clip("run").stride), float(character.clip("strafe_left").stride),
                          float(character.clip("strike").markers.get("impact", 0.5)), int(upper_body_mask))


class Survivor:
    def __init__(self, motion: SurvivorMotion, position=(0.0, 0.0)):
        self.motion = motion
        self.position = np.asarray(position, np.float64).copy()
        self.heading = np.array([0.0, 1.0])  # the front (x, z): (sin yaw, cos yaw)
        self.velocity = np.zeros(2)
        self.phase = 0.0
        self.action, self.action_time, self._landed = NONE, 0.0, False
        self.health = HEALTH
        self.kills = 0
        self.round_time = 0.0
        self.best_time = 0.0
        self.rounds = 1
        self.blows = 0  # zombie blows taken this round
        self.since_blow = 0.0  # seconds since the last blow landed (regeneration waits for REGEN_DELAY of them)
        self._health = float(HEALTH)  # health with the fraction regeneration has added (health is its whole part)
        self.history: list[dict] = []  # each ended round: its number, length, kills, blows taken and how it ended
        self._move = np.zeros(2)
        self._face: np.ndarray | None = None
        self._target: np.ndarray | None = None
        self._weights = (1.0, 0.0, 0.0)
        self._strafe_clip = motion.clip["strafe_left"]

    # -- input

    def command(self, move=(0.0, 0.0), face=None) -> None:
        """Move in a world direction (x, z; its length, at most 1, is the share of full speed) and face
        `face` (x, z), or where it moves when None. Cancels a walk to a point."""
        m = _pair(move, "move must be a finite (x, z) direction")
        length = float(np.hypot(*m))
        self._move = m / length if length > 1.0 else m
        self._face = None if face is None else _unit(face, "face")
        self._target = None

    def walk_to(self, point, face=None) -> None:
        """Run to a ground point (x, z) and stop there, facing `face` (x, z) on the way, or where it runs."""
        self._target = _pair(point, "ground point must be a finite (x, z)")
        self._face = None if face is None else _unit(face, "face")

    def strike(self) -> bool:
        """Swing the bat, unless a swing is under way. Returns whether a swing started."""
        if self.action == STRIKE or self.down:
            return False
        self.action, self.action_time, self._landed = STRIKE, 0.0, False
        return True

    def hurt(self, blows: int) -> None:
        """`blows` zombie attacks landed: health down, a flinch (over a swing too)."""
        if blows <= 0 or self.down:
            return
        self.blows += int(blows)
        self._health = max(self._health - int(blows) * BLOW_DAMAGE, 0.0)
        self.health = int(self._health)
        self.since_blow = 0.0
        self.action, self.action_time, self._landed = HIT, 0.0, True

    @property
    def down(self) -> bool:
        return self.health <= 0

    def round_record(self) -> dict:
        """This round so far: its number, seconds, kills, blows taken, and "down" (health ran out) or
        "playing" (it goes on)."""
        return {"round": self.rounds, "length_s": round(self.round_time, 3), "kills": self.kills, "blows": self.blows,
                "end": "down" if self.down else "playing"}

    def new_round(self, position) -> None:
        """Health back, kills and the round's clock back to 0, at `position`; the best time is kept, and
        the ended round's record."""
        self.history.append(self.round_record())
        self.best_time = max(self.best_time, self.round_time)
        self.rounds += 1
        self.health, self.kills, self.round_time, self.blows = HEALTH, 0, 0.0, 0
        self._health, self.since_blow = float(HEALTH), 0.0
        self.position = np.asarray(position, np.float64).copy()
        self.velocity[:] = 0.0
        self.action, self.action_time, self._landed = NONE, 0.0, False
        self._target = None

    # -- stepping

    @property
    def yaw(self) -> float:
        return math.atan2(self.heading[0], self.heading[1])

    @property
    def left(self) -> np.ndarray:
        """The survivor's left in world (x, z): model +X turned by its heading."""
        return np.array([self.heading[1], -self.heading[0]])

    def step(self, dt: float, bounds=None) -> bool:
        """Advance dt seconds (clamped to 0.25, as the AI clamps): velocity toward the command, heading,
        phase and the action's clock; `bounds` ((lo x, lo z), (hi x, hi z)) keeps it in the world.
        Returns True in the step at which a swing lands."""
        if isinstance(dt, bool) or not isinstance(dt, (int, float, np.floating)) or not math.isfinite(dt) or dt < 0:
            raise PlayerError(f"dt must be a finite number >= 0, got {dt!r}")
        dt = min(float(dt), 0.25)
        m = self.motion
        if not self.down:
            self.round_time += dt
            self.since_blow += dt
            if self.since_blow >= REGEN_DELAY and self._health < HEALTH:
                self._health = min(self._health + REGEN_RATE * dt, float(HEALTH))
                self.health = int(self._health)
        move = self._move
        if self._target is not None:
            to = self._target - self.position
            dist = float(np.hypot(*to))
            move = to / dist * min(dist / 1.0, 1.0) if dist > 0.05 else np.zeros(2)
            if dist <= 0.05:
                self._target = None
        if self.down:
            move = np.zeros(2)
        desired = self._desired_velocity(move)
        change = desired - self.velocity
        size = float(np.hypot(*change))
        self.velocity += change * min(1.0, ACCEL * dt / max(size, 1e-12))
        self.position += self.velocity * dt
        if bounds is not None:
            lo, hi = np.asarray(bounds[0], np.float64), np.asarray(bounds[1], np.float64)
            outside = (self.position < lo) | (self.position > hi)
            self.position = np.clip(self.position, lo, hi)
            self.velocity[outside] = 0.0
        goal = self._face if self._face is not None else (self.velocity if np.hypot(*self.velocity) > 0.2 else None)
        if goal is not None:
            self._turn(goal, TURN_RATE * dt)
        # Locomotion: the run (forward, or backward), a strafe clip, idle, by the velocity in the survivor's frame.
        forward, sideways = float(self.velocity @ self.heading), float(self.velocity @ self.left)
        speed = math.hypot(forward, sideways)
        moving = min(speed / MOVING, 1.0)
        share = abs(forward) / max(abs(forward) + abs(sideways), 1e-12)
        self._weights = (1.0 - moving, moving * share, moving * (1.0 - share))
        self._strafe_clip = m.clip["strafe_left" if sideways >= 0 else "strafe_right"]
        if speed < 1e-6:
            rate = 1.0 / m.duration["idle"]
        elif share >= 0.5:
            rate = forward / m.run_stride  # backward: the run played backward
        else:
            rate = abs(sideways) / m.strafe_stride
        self.phase = float(advance_phase(np.array([self.phase]), rate * dt)[0])
        # The action's clock; a swing lands once, at its impact.
        landed = False
        if self.action != NONE:
            self.action_time += dt
            length = m.duration["strike" if self.action == STRIKE else "hit"]
            if self.action == STRIKE and not self._landed and self.action_time >= m.impact * length:
                self._landed = landed = True
            if self.action_time >= length:
                self.action, self.action_time = NONE, 0.0
        return landed

    def collide(self, keep_out, obstacles) -> None:
        """Out of the obstacles (`keep_out`: the AI's, which moves points out of them), its velocity into
        them stopped: it slides along a wall as the crowd does."""
        x, z = keep_out(self.position[:1], self.position[1:])
        moved = np.array([x[0], z[0]])
        if np.array_equal(moved, self.position):
            return
        self.position = moved
        gx, gz = obstacles.gradient(moved[:1], moved[1:])
        g = np.array([gx[0], gz[0]])
        self.velocity -= min(float(self.velocity @ g), 0.0) * g

    def _desired_velocity(self, move: np.ndarray) -> np.ndarray:
        """The velocity a move asks for: its direction at the speed the survivor has that way (run
        forward, back off slower, side-step slower still; an ellipse between them)."""
        length = float(np.hypot(*move))
        if length < 1e-9:
            return np.zeros(2)
        d = move / length
        f, s = float(d @ self.heading), float(d @ self.left)
        along = self.motion.run_speed if f >= 0 else BACK_SHARE * self.motion.run_speed
        top = 1.0 / math.sqrt((f / along) ** 2 + (s / STRAFE_SPEED) ** 2)
        return d * top * min(length, 1.0)

    def _turn(self, goal, step: float) -> None:
        g = np.asarray(goal, np.float64)
        g = g / max(float(np.hypot(*g)), 1e-12)
        angle = math.atan2(self.heading[0] * g[1] - self.heading[1] * g[0], float(self.heading @ g))
        turn = -max(-step, min(step, angle))  # toward the goal
        c, s = math.cos(turn), math.sin(turn)
        h = self.heading
        self.heading = np.array([c * h[0] + s * h[1], -s * h[0] + c * h[1]])
        self.heading /= float(np.hypot(*self.heading))

    # -- outputs

    def write_layers(self, out: np.ndarray) -> np.ndarray:
        """Its (1, 4, 4) float32 layers: idle, run, strafe, action (on the upper body), written into `out`."""
        m = self.motion
        out[:] = 0.0
        out[0, :, MASK] = -1.0
        w_idle, w_run, w_strafe = self._weights
        for layer, (clip, weight) in enumerate(((m.clip["idle"], w_idle), (m.clip["run"], w_run), (self._strafe_clip, w_strafe))):
            out[0, layer, CLIP] = clip
            out[0, layer, PHASE] = self.phase
            out[0, layer, WEIGHT] = weight
        if self.action != NONE:
            role = "strike" if self.action == STRIKE else "hit"
            length = m.duration[role]
            fade = min(self.action_time / CROSSFADE, (length - self.action_time) / CROSSFADE, 1.0)
            fade = max(fade, 0.0)
            out[0, 3, CLIP] = m.clip[role]
            out[0, 3, PHASE] = min(self.action_time / length, 1.0)
            if m.upper_body_mask >= 0:  # the legs go on moving: weight W against the locomotion's 1 shows W / (W + 1) = fade
                out[0, 3, WEIGHT] = min(fade / max(1.0 - fade, 1e-12), MAX_ACTION_WEIGHT)
                out[0, 3, MASK] = m.upper_body_mask
            else:
                out[0, :3, WEIGHT] *= 1.0 - fade
                out[0, 3, WEIGHT] = fade
        return out


def _pair(value, rule: str) -> np.ndarray:
    """`value` as a finite float64 (x, z), or PlayerError saying "the survivor's <rule>, got ..."."""
    try:
        a = np.asarray(value, np.float64).reshape(-1)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != (2,) or not np.all(np.isfinite(a)):
        shown = repr(value)
        raise PlayerError(f"the survivor's {rule}, got {shown if len(shown) <= 40 else shown[:37] + '...'}")
    return a


def _unit(v, what: str) -> np.ndarray:
    a = _pair(v, f"{what} must be a finite, non-zero (x, z) direction")
    length = float(np.hypot(*a))
    if length < 1e-9:
        raise PlayerError(f"the survivor's {what} must be a finite, non-zero (x, z) direction, got {v!r}")
    return a / length
