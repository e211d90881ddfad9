"""The crowd AI's think budget (issue 20): agents near the player or the camera, and every action,
step exactly as with the budget off; far wandering agents think every think_every substeps and
coast smoothly in between. (tests/test_ai.py runs every behaviour and stability test with the budget
on and off.)"""

from __future__ import annotations

import numpy as np
import pytest

from crowd.anim.roles import bake_roles, match_roles
from crowd.sim.ai import CrowdAI
from crowd.sim.config import HIT, WANDER, AIConfig, AIError
from crowd.sim.motion import motion_for

STEP = 1.0 / 60.0


@pytest.fixture(scope="module")
def motion(zombie):
    roles, _ = match_roles(zombie.clips)
    baked = bake_roles(zombie, roles)
    return motion_for(zombie, baked, roles)


def _isolated_cluster(motion, think_every: int) -> CrowdAI:
    """2,000 agents: 60 chase a player who stands still, in a 12 m disc around it, and the rest stand
    100 m and more away (wander_speed 0: they pick points but never walk), so nothing far moves or
    touches the near ones; whatever the budget does to the far agents cannot reach the near ones."""
    config = AIConfig(half_extent=300.0, wander_speed=0.0, think_every=think_every, think_from=0, think_radius=30.0,
                      reaction_min=0.0, reaction_max=0.0)
    ai = CrowdAI(2000, 9, motion, config)
    rng = np.random.default_rng(3)
    angle, radius = rng.uniform(0, 2 * np.pi, 60), np.sqrt(rng.uniform(4.0, 144.0, 60))
    ai.x[:60], ai.z[:60] = radius * np.cos(angle), radius * np.sin(angle)
    far = rng.uniform(100.0, 290.0, (2, 1940)) * rng.choice([-1.0, 1.0], (2, 1940))
    ai.x[60:], ai.z[60:] = far
    ai.tx[:], ai.tz[:] = ai.x, ai.z
    ai.player = np.array([0.0, 0.0])
    return ai


def test_near_agents_step_exactly_as_without_the_budget(motion):
    runs = []
    for think_every in (1, 8):
        ai = _isolated_cluster(motion, think_every)
        ai.set_config(ai.config)  # the exact set from the positions placed by hand
        for _ in range(300):
            ai.step(STEP)
        assert ai.budgeted() == (think_every > 1) and ai.check() == []
        runs.append(ai)
    off, on = runs
    assert on.counts()["chase"] + on.counts()["attack"] > 40  # they did come for the player
    near = slice(0, 60)
    for name in ("x", "z", "vx", "vz", "hx", "hz", "phase", "state", "action", "action_time", "state_time", "cooldown"):
        assert np.array_equal(getattr(off, name)[near], getattr(on, name)[near]), name
    assert np.array_equal(off.layers()[near], on.layers()[near])
    assert off.player_hits_taken == on.player_hits_taken


def test_a_hit_is_exact_at_once_and_far_agents_coast_every_substep(motion):
    """Separation made negligible (1 mm), so that each substep's motion can be checked exactly."""
    config = AIConfig(half_extent=200.0, think_every=8, think_from=0, think_radius=20.0, separation_radius=1e-3)
    ai = CrowdAI(3000, 4, motion, config)
    ai.player = np.array([0.0, 0.0])
    for _ in range(60):
        ai.step(STEP)
    assert np.count_nonzero(~ai._exact & (np.hypot(ai.vx, ai.vz) > 0.05)) > 500  # most of the crowd is budgeted, much of it walks
    # No stutter: between its thinks a far agent moves on every substep at its velocity, and its
    # phase at its rate; the block whose turn it is thinks, over the time since it last did.
    turns = 0
    for _ in range(16):
        b = ai.substeps % 8
        block = np.zeros(ai.n, bool)
        block[b * ai.n // 8: (b + 1) * ai.n // 8] = True
        coasting = ~ai._exact & ~block
        x, z, vx, vz, phase, rate, hx, hz = (a.copy() for a in (ai.x, ai.z, ai.vx, ai.vz, ai.phase, ai.phase_rate, ai.hx, ai.hz))
        pending = ai._pending.copy()
        ai.step(STEP)
        # Headings turn by at most one substep's turn, thinking or not (a think does not turn them at once).
        turned = np.abs(np.arctan2(hx * ai.hz - hz * ai.hx, hx * ai.hx + hz * ai.hz))
        assert turned.max() <= config.turn_rate * STEP + 1e-9
        turns += np.count_nonzero(turned[coasting] > 1e-12)
        # ... and a turning one pivots on the foot it stands on (turn_about_planted_foot): a shift of at
        # most that foot's distance from its origin (half a metre) times the turn.
        off_x = ai.x[coasting] - (x[coasting] + vx[coasting] * STEP)
        off_z = ai.z[coasting] - (z[coasting] + vz[coasting] * STEP)
        straight = turned[coasting] <= 1e-12
        assert np.all(off_x[straight] == 0.0) and np.all(off_z[straight] == 0.0)
        assert np.all(np.hypot(off_x, off_z) <= 0.5 * turned[coasting] + 1e-12)
        assert np.array_equal(ai.vx[coasting], vx[coasting])
        walking = coasting & (rate > 0)
        assert np.allclose(np.mod(ai.phase[walking] - phase[walking], 1.0), rate[walking] * STEP, atol=1e-12)
        thought = block & ~ai._exact
        assert np.all(ai._pending[thought] == 0.0) and np.all(ai._pending[coasting] == pending[coasting] + STEP)
    assert turns > 50  # far agents did go on turning between their thinks
    # A far agent struck by the player plays its hit from the next substep on, exactly.
    victim = int(np.flatnonzero(~ai._exact & (ai.state == WANDER))[0])
    ai.hit([victim])
    assert ai.state[victim] == HIT and ai._exact[victim]
    ai.step(STEP)
    assert ai.action_time[victim] == STEP


def test_a_bad_think_budget_is_one_line(motion):
    with pytest.raises(AIError, match="think_radius must be >= notice_radius"):
        CrowdAI(10, 1, motion, AIConfig(think_every=4, think_radius=5.0, notice_radius=14.0))
    for bad in ({"think_every": 0}, {"think_every": 65}, {"think_from": -1}, {"think_radius": -1.0}):
        with pytest.raises(AIError):
            CrowdAI(10, 1, motion, AIConfig(**bad))


def test_agents_the_player_leaves_behind_go_back_to_the_budget(motion):
    """300 zombies around the player, none of which will ever chase (a reaction of 1,000 s), are all
    exact; once the player is 1 km away they are budgeted again at the next substep."""
    config = AIConfig(half_extent=2000.0, think_every=8, think_from=0, think_radius=30.0, reaction_min=1000.0, reaction_max=1000.0)
    ai = CrowdAI(3000, 2, motion, config)
    rng = np.random.default_rng(5)
    ai.x[:300], ai.z[:300] = rng.uniform(-15.0, 15.0, (2, 300))
    ai.tx[:300], ai.tz[:300] = ai.x[:300], ai.z[:300]
    ai.player = np.array([0.0, 0.0])
    ai.set_config(ai.config)
    for _ in range(10):
        ai.step(STEP)
    assert ai.exact_count() >= 295 and ai._exact[:300].all()
    ai.player = np.array([1000.0, 1000.0])
    ai.step(STEP)
    near_new = np.hypot(ai.x - 1000.0, ai.z - 1000.0) < 30.0
    assert not ai._exact[:300].any() and ai.exact_count() <= int(np.count_nonzero(near_new))
