"""An agent's think, in two halves around separation: timers and transitions (notice, chase, attack, the
end of a hit or a death, respawn), steering and motion; then heading and locomotion phase. Run per range
of agents (the think, apply and finish phases), on views or gathered copies of the crowd's arrays."""

from __future__ import annotations

import math

import numpy as np

from .config import ACT_ATTACK, ATTACK, ATTACK_IMPACT, BLOW_REACH, CHASE, DEAD, DYING, HIT, NO_ACTION, WANDER
from .locomotion import advance_phase, blended_stride, locomotion_weights, phase_rate, turn_about_planted_foot
from .spawn import _WANDER


class _Agents:
    """Some of the crowd's per-agent arrays under the AI's own names, for one think: views for a slice
    (a process's range, its part of a think block), gathered copies for an index array (the exact
    agents). ``commit()`` writes back the copies, and every array the think rebound (np.where makes new
    ones). ``ids(local)``: the crowd's numbers of its agents, for the keyed random draws."""

    def __init__(self, ai: ThinkMixin, selection):
        self._ai, self._selection = ai, selection
        self.ids = (lambda local: selection.start + local) if isinstance(selection, slice) else (lambda local: selection[local])
        self._was = {}
        for name in ai._names():
            self._was[name] = getattr(ai, name)[selection]
            setattr(self, name, self._was[name])

    def commit(self) -> None:
        gathered = not isinstance(self._selection, slice)
        for name, was in self._was.items():
            now = getattr(self, name)
            if now is was and not gathered:
                continue  # changed in place, through the view
            getattr(self._ai, name)[self._selection] = now


class ThinkMixin:
    """CrowdAI's part that thinks: the think, apply and finish phases of a range of agents."""

    def _think_range(self, lo: int, hi: int, h: float, block, have_pairs: bool) -> tuple:
        """The think phase of agents lo..hi, or under the budget (`block`: the block's bounds and this
        process's slice of it) of this process's share: (strikes on the player, respawns, the largest
        squared move since the neighbour lists' build among the agents it moved, 0 without lists)."""
        hits, self._respawns = self.player_hits_taken, 0
        if block is None:  # every agent thinks
            group = _Agents(self, slice(lo, hi))
            self._range = {"near": self._think_a(group, h, h)}
            group.commit()
            moved = [(slice(lo, hi), None)]
        else:
            self._range = self._budgeted_think(lo, hi, h, *block)
            # What this process moved: its range's coasting agents, its slice of the block, its exact agents.
            moved = [(slice(lo, hi), self._range["coasting"]), (self._range["block"], None), (self._range["exact"], None)]
        farthest = 0.0
        if have_pairs:
            for agents, mask in moved:
                mx, mz = self.x[agents] - self._pairs_x[agents], self.z[agents] - self._pairs_z[agents]
                moved2 = mx * mx + mz * mz if mask is None else np.where(mask, mx * mx + mz * mz, 0.0)
                if moved2.size:
                    farthest = max(farthest, float(np.max(moved2)))
        return (float(self.player_hits_taken - hits), float(self._respawns), farthest)

    def _apply_range(self, lo: int, hi: int, push) -> None:
        """Agents lo..hi: their separation pushes (``_push_range``'s), then the world's bounds."""
        if push is not None:
            agents, push_x, push_z = push
            self.x[agents] += push_x
            self.z[agents] += push_z
            if self.config.plant_feet:
                self._step_with_push(agents, push_x, push_z)
        self._bound(lo, hi)
        if self.obstacles is not None:
            self._clear_obstacles(lo, hi)

    def _step_with_push(self, agents: np.ndarray, push_x: np.ndarray, push_z: np.ndarray) -> None:
        """A push along a walking agent's heading moves its body as its own steps do, so its locomotion
        phase moves with it (backward for a push from the front): the planted foot stays where it stands.
        In a blend at walk-or-run weight w (1 - idle's), the stance foot moves w x the blended stride per
        cycle; below w = 1/2 the push is left a slide rather than spin the legs."""
        m = self._m(agents=agents)
        speed = np.sqrt(self.vx[agents] ** 2 + self.vz[agents] ** 2)
        w_idle, _, _, run_t = locomotion_weights(m, speed, self.walk_top[agents], self.speed_factor[agents])
        stepping = (w_idle <= 0.5) & (self.state[agents] < DYING)
        if not np.any(stepping):
            return
        stride = (1.0 - w_idle) * blended_stride(m, run_t, self.scale[agents])
        along = push_x * self.hx[agents] + push_z * self.hz[agents]
        phase = self.phase[agents]
        advance_phase(phase, np.where(stepping, along / np.maximum(stride, 1e-9), 0.0))
        self.phase[agents] = phase

    def _finish_range(self, lo: int, hi: int, h: float) -> None:
        """The finish phase: heading and phase of this process's agents (and, without the budget, their
        pushes and bounds first)."""
        state, self._range = self._range, None
        if "near" in state:
            self._apply_range(lo, hi, state["push"])
            group = _Agents(self, slice(lo, hi))
            self._think_b(group, h, h, h, *state["near"])
            group.commit()
            return
        exact, block = state["exact"], state["block"]
        group = _Agents(self, exact)
        self._think_b(group, h, h, h, *state["near_exact"])
        group.commit()  # (the copy holds the old flags: commit first, then say who stays exact)
        self._exact[exact] = self._must_be_exact(group)
        group = _Agents(self, block)
        self._think_b(group, state["think_h"], state["move_h"], h, *state["near_block"])
        self._exact[block] |= self._must_be_exact(group)  # from now on with the exact ones (their pending time is 0)
        group.commit()

    def _think_a(self, a, h, move):
        """The first half of a substep for the agents of `a` (the crowd itself, or an ``_Agents``):
        timers and transitions, steering and velocity over `h` seconds (a scalar, or per agent: the
        time since they last thought), and this substep's motion over `move`. Returns what the second
        half needs."""
        cfg = self.config
        px, pz = float(self.player[0]), float(self.player[1])
        to_px, to_pz = px - a.x, pz - a.z
        dist = np.sqrt(to_px * to_px + to_pz * to_pz)
        state = a.state
        a.state_time += h
        a.action_time += h
        a.cooldown -= h

        # Transitions; events are rare, so they work on index lists.
        length = self.action_length(a.action, self._kind_of(a))
        # A blow lands at its swing's impact, on a player still within reach of it: one who moves away dodges it.
        swinging = np.flatnonzero(state == ATTACK)
        if swinging.size:
            impact = ATTACK_IMPACT * length[swinging]
            t, step = a.action_time[swinging], (h[swinging] if np.ndim(h) else h)
            lands = (t >= impact) & (t - step < impact) & (dist[swinging] < cfg.attack_reach * BLOW_REACH)
            self.player_hits_taken += int(np.count_nonzero(lands))
        done = np.flatnonzero(a.action_time >= length)
        if done.size:
            s = state[done]
            back = done[(s == ATTACK) | (s == HIT)]
            a.cooldown[back] = np.where(state[back] == ATTACK, cfg.attack_cooldown, 0.0)
            state[back] = CHASE
            a.action[back] = NO_ACTION
            died = done[s == DYING]
            state[died] = DEAD
            a.state_time[died] = 0.0
        respawn = np.flatnonzero((a.state_time >= cfg.corpse_time) & (state == DEAD))
        self._spawn(a, respawn, anywhere=False)
        grown = cfg.alert(self.time)
        near = dist < cfg.notice_radius + grown
        a.aware += h
        a.aware[~near] = 0.0
        wandering = state == WANDER
        notice = np.flatnonzero(wandering & near & (a.aware >= a.reaction))  # (near: a reaction of 0 notices nobody far)
        state[notice] = CHASE
        lost = np.flatnonzero((dist > cfg.forget_radius + grown) & (state == CHASE))
        state[lost] = WANDER
        if np.any(self._role_clip["attack"] >= 0):
            ready = (dist < cfg.attack_reach) & (a.cooldown <= 0.0) & (state == CHASE)
            if len(self.motions) > 1:
                ready &= self._role_clip["attack"][a.kind] >= 0  # characters without an attack clip do not strike
            strike = np.flatnonzero(ready & (h > 0.0) if np.ndim(h) else ready)  # agents given no time strike nobody
            self._start(strike, ATTACK, ACT_ATTACK, a)

        # Desired velocity: wanderers walk slowly to their target, chasers to the player, the rest stand.
        chasing = state == CHASE
        wandering = state == WANDER
        a.pause -= h  # (everyone's, wandering or not: a per-agent rule, the same on the GPU)
        if wandering.any():
            self._wander(a, wandering, h)
        dx = np.where(chasing, to_px, a.tx - a.x)
        dz = np.where(chasing, to_pz, a.tz - a.z)
        if self.obstacles is not None and chasing.any():  # around the buildings, by the flow field to the player
            c = np.flatnonzero(chasing)
            ux, uz = self._flow_directions(a.x[c], a.z[c], to_px[c], to_pz[c])
            dx[c], dz[c] = ux * dist[c], uz * dist[c]
        d = np.sqrt(dx * dx + dz * dz)
        top = np.where(chasing, a.chase_top, cfg.wander_speed * a.walk_top * (wandering & (a.pause <= 0.0)))
        gap = np.where(chasing, d - 0.8 * cfg.attack_reach, d)
        speed = top * np.minimum(np.maximum(gap * (1.0 / cfg.arrive_distance), 0.0), 1.0)
        scale = speed / np.maximum(d, 1e-9)
        # Velocity with limited acceleration; the dying and the dead stop at once (no sliding corpses).
        cx, cz = dx * scale - a.vx, dz * scale - a.vz
        limit = np.minimum(1.0, (cfg.max_accel * h) / np.maximum(np.sqrt(cx * cx + cz * cz), 1e-12))
        a.vx += cx * limit
        a.vz += cz * limit
        still = np.flatnonzero(state >= DYING)
        a.vx[still] = 0.0
        a.vz[still] = 0.0
        a.x += a.vx * move
        a.z += a.vz * move
        return to_px, to_pz, dist

    def _think_b(self, a, h, move, substep: float, to_px, to_pz, dist) -> None:
        """The second half, after separation: heading (turned by at most turn_rate x `substep`, this
        substep's length, however long since the agent last thought: a budgeted agent goes on turning
        toward the same goal between thinks, see _coast_turns) and the locomotion phase (advanced over
        `move`)."""
        cfg = self.config
        state = a.state
        # Heading: a unit vector turned toward the motion (or toward the player while attacking) by at
        # most turn_rate * h, rotating by a fixed angle instead of going through angles (no trig per agent).
        speed = np.sqrt(a.vx * a.vx + a.vz * a.vz)
        attacking = state == ATTACK
        gx = np.where(attacking, to_px, a.vx)
        gz = np.where(attacking, to_pz, a.vz)
        glen = np.where(attacking, dist, speed)
        turning = (glen > 0.05) & (state < DYING)
        budgeted = np.ndim(h) > 0
        if budgeted:
            turning &= h > 0.0  # agents that do not think here (exact ones inside a block) keep their heading
        hx0, hz0 = a.hx, a.hz
        m = self._m(a)
        weights = locomotion_weights(m, speed, a.walk_top, a.speed_factor)  # (idle, walk, run, run share)
        ux, uz = self._turn(a, turning, gx, gz, glen, cfg.turn_rate * substep)
        self._pivot(a, np.flatnonzero(turning & (a.action == NO_ACTION) & ((a.hx != hx0) | (a.hz != hz0))), hx0, hz0,
                    weights[:3])
        if budgeted:  # those not at their goal yet turn on toward it, a substep's worth at a time, until they think again
            np.copyto(a._goal_x, ux)
            np.copyto(a._goal_z, uz)
            np.copyto(a._coast_turn, turning & ((a.hx != ux) | (a.hz != uz)))

        # Locomotion phase: speed over the blended stride (idle plays at its own rate while standing),
        # for the share of the motion along the heading. A heading that lags the motion (it turns at
        # turn_rate) walks forward only that share; the planted feet keep pace with it, and the rest is a
        # sideways slide no forward clip can follow (crowd.anim.foot_skate measures it).
        run_t = weights[3]
        forward = np.minimum(np.maximum((a.vx * a.hx + a.vz * a.hz) / np.maximum(speed, 1e-12), 0.0), 1.0)
        rate = phase_rate(m, speed, a.walk_top, run_t, a.scale) * np.where(speed > 0.0, forward, 1.0)
        advance_phase(a.phase, rate * move)
        if self.budgeted():
            a.phase_rate[:] = rate  # what the phase advances by until the agent thinks again

    def _turn(self, a, turning: np.ndarray, gx, gz, glen, step: float):
        """Turn each heading toward (gx, gz) by at most `step` radians. Headings within `step` of their
        goal snap to it; only the few farther off are rotated, by a fixed angle (no trig per agent).
        Rotation keeps the length to within rounding, about 1e-16 per step: 1e-10 after ten hours.
        Returns the goal directions."""
        inv = 1.0 / (glen + 1e-30)
        ux, uz = gx * inv, gz * inv
        hx, hz = a.hx, a.hz
        near = hx * ux + hz * uz >= math.cos(step)
        snap = turning & near
        far = np.flatnonzero(turning & ~near)
        a.hx = np.where(snap, ux, hx)
        a.hz = np.where(snap, uz, hz)
        if far.size:
            a.hx[far], a.hz[far] = _rotate_toward(hx[far], hz[far], ux[far], uz[far], step)
        return ux, uz

    def _pivot(self, a, turned: np.ndarray, hx0: np.ndarray, hz0: np.ndarray, weights) -> None:
        """Shift the agents `turned` (indices into the group `a`) so that they turned about the foot they
        stand on (turn_about_planted_foot); `weights`: the group's idle, walk and run weights."""
        if not turned.size or not self.config.plant_feet:
            return
        kind = a.kind[turned] if len(self.motions) > 1 else np.zeros(len(turned), np.int8)
        for k, m in enumerate(self.motions):  # each character pivots on its own feet
            if m.pivots is None:
                continue
            mine = turned if len(self.motions) == 1 else turned[kind == k]
            if not mine.size:
                continue
            dx, dz = turn_about_planted_foot(m, a.phase[mine], [w[mine] for w in weights], hx0[mine], hz0[mine],
                                             a.hx[mine], a.hz[mine], a.scale[mine])
            x, z = self._inside(a.x[mine] + dx, a.z[mine] + dz)
            if self.obstacles is not None:  # (a pivot by a wall must not step into it: this comes after the apply phase's clearing)
                x, z = self.keep_out(x, z)
            a.x[mine], a.z[mine] = x, z

    def _inside(self, x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ground positions clamped into the world square (a pivot at its edge must not step out)."""
        e = self.half_extent
        return (np.minimum(np.maximum(x, self.origin[0] - e), self.origin[0] + e),
                np.minimum(np.maximum(z, self.origin[1] - e), self.origin[1] + e))

    def _bound(self, lo: int, hi: int) -> None:
        """World bounds for agents lo..hi: clamp, and stop the velocity component that points out."""
        for p, v, o in ((self.x[lo:hi], self.vx[lo:hi], self.origin[0]), (self.z[lo:hi], self.vz[lo:hi], self.origin[1])):
            low, high = o - self.half_extent, o + self.half_extent
            out = np.flatnonzero((p < low) | (p > high))
            if out.size:
                p[out] = np.minimum(np.maximum(p[out], low), high)
                v[out] = 0.0

    def _wander(self, a, wandering: np.ndarray, h) -> None:
        dx, dz = a.tx - a.x, a.tz - a.z
        idx = np.flatnonzero(wandering & (dx * dx + dz * dz < 0.16) & (a.pause <= 0.0))
        if idx.size:
            cfg = self.config
            draw = self._draws(a.ids(idx), _WANDER, 4)  # keyed by agent and substep (see _draws)
            angle = math.pi * (2.0 * draw[0] - 1.0)
            radius = cfg.wander_radius * np.sqrt(0.1 + 0.9 * draw[1])
            inner = self.half_extent - 0.5
            a.tx[idx] = np.clip(a.x[idx] + radius * np.sin(angle), self.origin[0] - inner, self.origin[0] + inner)
            a.tz[idx] = np.clip(a.z[idx] + radius * np.cos(angle), self.origin[1] - inner, self.origin[1] + inner)
            a.pause[idx] = np.where(draw[2] < 0.5, 1.0 + 3.0 * draw[3], 0.0)
            if self.obstacles is not None:  # a target in a building is moved out to the street beside it
                a.tx[idx], a.tz[idx] = self.keep_out(a.tx[idx], a.tz[idx])


def _rotate_toward(hx, hz, ux, uz, step: float):
    """Unit headings (hx, hz) rotated by the angle `step` toward the unit directions (ux, uz)."""
    sin, cos = math.sin(step), math.cos(step)
    s = np.where(hx * uz - hz * ux >= 0.0, -sin, sin)  # toward the goal
    return cos * hx + s * hz, cos * hz - s * hx
