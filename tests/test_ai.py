"""The crowd AI: behaviour, determinism, and stability on stiff and extreme cases.

Every test checks the invariants of `CrowdAI.check()` as it goes: no NaN or Inf in the agent state, no
agent outside the world bounds, and every layer weight finite and non-negative.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from crowd.sim.ai import CrowdAI, PlayerScript
from crowd.sim.config import ATTACK, CHASE, DEAD, DYING, HIT, LAYERS, WANDER, AIConfig, AIError
from crowd.sim.locomotion import turn_about_planted_foot
from crowd.sim.motion import FOOT_SAMPLES, motion_for
from crowd.frame import CLIP, MASK, PHASE, WEIGHT, validate_layers
from crowd.anim.roles import bake_roles, match_roles

STEP = 1.0 / 60.0


@pytest.fixture(autouse=True, params=["budget off", "budget on"])
def think_budget(request, monkeypatch):
    """Every test here runs twice: with the think budget off, and on for any crowd (think_from 0) with
    the smallest radius allowed, so that most agents of these small worlds are far and budgeted."""
    if request.param == "budget off":
        over = {"think_every": 1}
    else:
        over = {"think_every": 8, "think_from": 0}
    validate = AIConfig.validate

    def with_budget(config: AIConfig) -> AIConfig:  # what CrowdAI keeps of any config it is given
        radius = {"think_radius": config.notice_radius} if "think_from" in over else {}
        return validate(dataclasses.replace(config, **over, **radius))

    monkeypatch.setattr(AIConfig, "validate", with_budget)
    return request.param


@pytest.fixture(scope="module")
def motion(zombie):
    roles, _ = match_roles(zombie.clips)
    baked = bake_roles(zombie, roles)
    return motion_for(zombie, baked, roles)


def run(ai: CrowdAI, steps: int, dt: float = STEP, script: PlayerScript | None = None, check_every: int = 10) -> None:
    for k in range(steps):
        if script is not None:
            script.update(ai)
        ai.step(dt)
        if k % check_every == 0 or k == steps - 1:
            assert ai.check() == [], f"step {k}"


def nearest_neighbour(pos: np.ndarray) -> np.ndarray:
    d = np.sqrt(((pos[:, None, :] - pos[None]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    return d.min(axis=1)


def test_same_seed_same_crowd_and_another_seed_another(motion):
    runs = []
    for seed in (5, 5, 6):
        ai = CrowdAI(300, seed, motion)
        run(ai, 240, script=PlayerScript(ai.half_extent * 0.5))
        runs.append((ai.pos, ai.yaw, ai.state.copy(), ai.layers()))
    for a, b in zip(runs[0], runs[1]):
        assert np.array_equal(a, b)
    assert not np.array_equal(runs[0][0], runs[2][0])


def test_dt_is_clamped_and_stepped_in_equal_substeps(motion):
    ai = CrowdAI(50, 1, motion)
    before = ai.pos
    assert ai.step(0.0) == 0 and np.array_equal(ai.pos, before) and ai.time == 0.0
    assert ai.step(1e-7) == 1
    assert ai.step(10.0) == math.ceil(ai.config.max_dt / ai.config.substep)  # a 10 s frame runs as 0.25 s
    assert ai.time == pytest.approx(0.25 + 1e-7)
    assert ai.step(1 / 30) == 2
    assert ai.check() == []
    for bad in (-0.1, float("nan"), float("inf"), "0.1", None, True):
        with pytest.raises(AIError, match="dt"):
            ai.step(bad)
    assert ai.check() == []  # a refused step changes nothing


def test_dt_spikes_and_zero_frames_stay_stable(motion):
    ai = CrowdAI(500, 2, motion)
    script = PlayerScript(ai.half_extent * 0.5)
    rng = np.random.default_rng(0)
    for k in range(300):
        script.update(ai)
        ai.step(float(rng.choice([0.0, 1e-6, STEP, 0.1, 10.0])))
        if k % 25 == 0:
            assert ai.check() == []
    assert ai.check() == []


def test_stiff_separation_stays_bounded(motion):
    """stiffness x dt = 1e6 x 0.25: the correction is clamped to the overlap, so nothing overshoots."""
    config = AIConfig(separation_stiffness=1e6, substep=0.25, max_dt=0.25, half_extent=30.0)
    ai = CrowdAI(400, 3, motion, config)
    rng = np.random.default_rng(1)
    ai.x[:] = rng.uniform(-1.5, 1.5, ai.n)
    ai.z[:] = rng.uniform(-1.5, 1.5, ai.n)
    ai.player = np.array([500.0, 500.0])  # out of reach: nobody chases
    top_speed = motion.run_speed * config.speed_max
    packed = np.median(nearest_neighbour(ai.pos))
    for _ in range(40):
        before = ai.pos
        ai.step(0.25)
        assert ai.check() == []
        moved = np.linalg.norm(ai.pos - before, axis=1)
        # Walking at most top speed, plus at most half the separation radius of correction.
        assert moved.max() <= top_speed * 0.25 + 0.5 * config.separation_radius + 1e-9
    assert packed < 0.1 and np.median(nearest_neighbour(ai.pos)) > 0.45  # from a 3 m square toward 0.75 m apart


def test_thousand_agents_spawned_at_one_point_spread_out(motion):
    ai = CrowdAI(1000, 4, motion, AIConfig(half_extent=40.0))
    ai.x[:] = 5.0
    ai.z[:] = -3.0
    ai.player = np.array([200.0, 200.0])
    run(ai, 600, check_every=50)
    nn = nearest_neighbour(ai.pos)
    assert nn.min() > 0.3 and np.median(nn) > 0.55  # separation radius 0.75 m
    assert ai.pos.std(axis=0).mean() > 4.0


def test_reused_neighbour_list_holds_every_close_pair(motion):
    """The separation keeps its pair list across substeps; whenever it is used, it must contain every
    pair of living agents closer than the separation radius, as an all-pairs search finds them."""
    ai = CrowdAI(500, 11, motion, AIConfig(half_extent=14.0, health=1))
    script = PlayerScript(ai.half_extent * 0.5)
    r = ai.config.separation_radius
    reused = 0
    for step in range(240):
        script.update(ai)
        builds = ai.pair_builds
        ai.step(STEP)  # one substep: the list it pushed with was built in it or kept from before
        reused += ai.pair_builds == builds
        i, j = ai.neighbour_list()
        listed = {(min(a, b), max(a, b)) for a, b in zip(i.tolist(), j.tolist())}
        pos, alive = ai.pos, np.flatnonzero(ai.alive())
        d = np.linalg.norm(pos[alive, None] - pos[None, alive], axis=2)
        a, b = np.nonzero(np.triu(d < r, k=1))
        close = set(zip(alive[a].tolist(), alive[b].tolist()))
        assert close <= listed, f"step {step}: {len(close - listed)} close pairs missing from the list"
    assert 120 < reused < 240  # the list was both reused and rebuilt
    assert ai.counts()["dying"] + ai.counts()["dead"] > 0  # with agents dying along the way


def test_far_from_origin_the_crowd_behaves_the_same(motion):
    """Float64 positions: a world centred 1e5 m out gives the same relative motion (the renderer's
    camera-relative drawing is tested in test_smoke)."""
    results = []
    for origin in ((0.0, 0.0), (1.0e5, -1.0e5)):
        ai = CrowdAI(200, 7, motion, origin=origin)
        run(ai, 300, script=PlayerScript(ai.half_extent * 0.5))
        results.append(ai.pos - np.asarray(origin))
    assert np.abs(results[0] - results[1]).max() < 1e-5


def test_agent_count_changes_at_run_time(motion):
    ai = CrowdAI(200, 8, motion)
    script = PlayerScript(ai.half_extent * 0.5)
    run(ai, 30, script=script)
    kept = ai.pos[:200].copy()
    kept_tint = ai.tint.copy()
    for n in (10_000, 0, 200):
        ai.resize(n)
        script.radius = ai.half_extent * 0.5
        if n == 10_000:
            assert np.array_equal(ai.pos[:200], kept) and np.array_equal(ai.tint[:200], kept_tint)
        run(ai, 30, script=script)
        assert ai.n == n and ai.layers().shape == (n, LAYERS, 4)
    with pytest.raises(AIError, match="agent count"):
        ai.resize(-1)


def test_layers_are_valid_processor_input(motion):
    ai = CrowdAI(2000, 9, motion)
    script = PlayerScript(ai.half_extent * 0.2)
    run(ai, 200, script=script)
    ai.hit(np.arange(0, 2000, 7))
    run(ai, 30, script=script)
    layers = ai.layers()
    validate_layers(layers, 6, 1, LAYERS)  # clip indices, masks, finite weights: the processor accepts it
    assert np.all(layers[..., WEIGHT] >= 0) and np.all(np.isfinite(layers))
    assert np.all((layers[..., PHASE] >= 0) & (layers[..., PHASE] <= 1))
    out = np.empty((ai.n, LAYERS, 4), np.float32)
    assert ai.write_layers(out) is out
    with pytest.raises(AIError, match="layers must be"):
        ai.write_layers(np.empty((ai.n, 3, 4), np.float32))


def test_notice_chase_attack(motion):
    ai = CrowdAI(2, 10, motion, AIConfig(half_extent=40.0))
    ai.x[:] = [5.0, 35.0]
    ai.z[:] = [0.0, 35.0]
    ai.player = np.zeros(2)
    run(ai, int(15 / STEP))  # a shambler covers 0.56 m/s: 4 m in about 8 s, then slows on arrival
    assert ai.state[1] == WANDER  # 49 m away: never noticed
    assert ai.player_hits_taken >= 1  # the near one came and swung
    assert ai.state[0] in (ATTACK, CHASE)
    assert np.hypot(ai.x[0], ai.z[0]) < ai.config.attack_reach + 0.2


def test_walk_phase_follows_ground_speed_so_feet_do_not_slide(motion):
    ai = CrowdAI(1, 11, motion, AIConfig(half_extent=200.0, speed_min=1.0, speed_max=1.0, runner_share=0.0))
    ai.x[:] = 0.0
    ai.z[:] = 0.0
    ai.player = np.array([0.0, 20.0])
    ai.aware[:] = 10.0
    ai.state[:] = CHASE
    run(ai, 120)  # reach walking speed
    z0, phase0 = ai.z[0], ai.phase[0]
    run(ai, 120)
    travelled = ai.z[0] - z0
    stride = motion.walk_stride * float(ai.scale[0])  # the agent's size scales its stride
    cycles = (ai.phase[0] - phase0) % 1.0 + int(travelled / stride)
    layers = ai.layers()
    assert layers[0, 1, WEIGHT] == pytest.approx(1.0)  # all walk at the walk speed
    assert cycles * stride == pytest.approx(travelled, rel=0.01)


def test_hit_death_lie_still_and_respawn_at_an_edge(motion):
    config = AIConfig(half_extent=30.0, corpse_time=2.0)
    ai = CrowdAI(3, 12, motion, config)
    ai.player = np.array([100.0, 100.0])
    ai.hit([0])
    assert ai.state[0] == HIT and ai.health[0] == config.health - 1
    run(ai, 6)
    fade_in = ai.layers()[0, 3]
    assert fade_in[CLIP] == motion.clip["hit"] and fade_in[MASK] == -1 and 0 < fade_in[WEIGHT] < 1
    for _ in range(config.health):
        ai.hit([0, 99, -1])  # unknown indices are ignored
    assert ai.state[0] == DYING
    run(ai, int((motion.duration["death"] + 0.1) / STEP))
    assert ai.state[0] == DEAD
    lying = ai.pos[0].copy()
    layers = ai.layers()[0]
    assert layers[3, WEIGHT] == 1.0 and layers[3, PHASE] == 1.0 and np.all(layers[:3, WEIGHT] == 0)
    ai.hit([0])  # the dead take no hits
    run(ai, int(1.5 / STEP))
    assert ai.state[0] == DEAD and np.array_equal(ai.pos[0], lying)
    run(ai, int(1.0 / STEP))
    assert ai.state[0] == WANDER and ai.health[0] == config.health
    edge = config.half_extent - 0.5
    assert max(abs(ai.x[0]), abs(ai.z[0])) == pytest.approx(edge, abs=0.2)


def test_attack_plays_on_the_upper_body_with_cross_fades(motion):
    ai = CrowdAI(1, 13, motion, AIConfig(crossfade=0.25, start_clear=0.0))
    ai.player = np.array([500.0, 500.0])
    ai._start(np.array([0]), ATTACK, 1)
    shares = []
    for _ in range(int(motion.duration["attack"] / STEP) - 1):
        ai.step(STEP)
        layer = ai.layers()[0, 3]
        assert layer[MASK] == 0 and layer[CLIP] == motion.clip["attack"]
        shares.append(layer[WEIGHT] / (layer[WEIGHT] + 1.0))  # the upper body's share against locomotion
    shares = np.array(shares)
    assert shares[0] < 0.1 and shares.max() > 0.99 and shares[-1] < 0.1  # in over 0.25 s, out over 0.25 s
    assert np.all(np.abs(np.diff(shares)) <= STEP / 0.25 + 1e-6)  # no pops
    run(ai, 10)
    assert ai.state[0] == CHASE or ai.state[0] == WANDER


def test_bad_ai_settings_get_one_line_errors(motion):
    for bad, words in ((dict(substep=0.0), "substep"), (dict(separation_stiffness=-1.0), "separation_stiffness"),
                       (dict(notice_radius=float("nan")), "notice_radius"), (dict(forget_radius=1.0), "forget_radius"),
                       (dict(health=0), "health"), (dict(max_dt=100.0), "max_dt")):
        with pytest.raises(AIError, match=words):
            CrowdAI(10, 1, motion, AIConfig(**bad))
    with pytest.raises(AIError, match="origin"):
        CrowdAI(10, 1, motion, origin=(float("inf"), 0.0))



def test_a_tiny_separation_radius_in_a_huge_world_needs_no_huge_grid(motion):
    """1 mm between 2,000 zombies across 10 km: the neighbour grid's cells would be 20 billion; its cells
    widen to about 4 an agent instead, and every close pair is still found."""
    ai = CrowdAI(2000, 6, motion, AIConfig(half_extent=5000.0, separation_radius=1e-3, wander_speed=0.0))
    ai.x[:10], ai.z[:10] = 100.0 + np.arange(10) * 2e-4, 50.0  # ten agents closer than the radius
    ai.player = np.array([4000.0, 4000.0])  # nobody chases, nobody walks: only separation moves the ten
    run(ai, 60)
    assert nearest_neighbour(ai.pos[:10]).min() > 5e-4  # they started 0.2 mm apart


def test_a_push_along_the_heading_moves_the_phase_as_a_step_would(motion):
    """A walking agent pushed forward by d covers d of ground its feet did not step: its locomotion
    phase moves on by d over the stride (back for a push from the front), so a planted foot stays put.
    A standing agent (idle's weight over a half) is left alone: its push is a slide."""
    ai = CrowdAI(8, 1, motion)
    agents = np.arange(3)
    ai.state[agents] = CHASE
    ai.hx[agents], ai.hz[agents] = 0.6, 0.8
    speeds = np.array([motion.walk_speed, motion.walk_speed, 0.1 * motion.walk_slowest * motion.walk_speed])
    ai.vx[agents], ai.vz[agents] = 0.6 * speeds, 0.8 * speeds
    ai.walk_top[agents] = motion.walk_speed
    ai.speed_factor[agents] = 1.0
    ai.scale[agents] = 1.0
    ai.phase[agents] = 0.5
    push = np.array([0.05, -0.05, 0.05])
    ai._step_with_push(agents, 0.6 * push, 0.8 * push)
    assert ai.phase[agents].tolist() == pytest.approx([0.5 + 0.05 / motion.walk_stride, 0.5 - 0.05 / motion.walk_stride, 0.5])
    sideways = np.array([0.05])
    before = ai.phase[:1].copy()
    ai._step_with_push(agents[:1], 0.8 * sideways, -0.6 * sideways)  # across the heading: no step can follow it
    assert ai.phase[:1] == pytest.approx(before)


def test_a_turn_pivots_on_the_planted_foot(motion, zombie):
    """turn_about_planted_foot shifts a turning agent so that the middle of its foot joints on the
    ground stays where it is in world space (the foot it stands on, not its origin, is the pivot); in a
    run's flight, with no foot down, it turns about its origin."""
    from crowd.asset.model import foot_joints
    from crowd.asset.pose import global_matrices, sample_clip

    assert motion.pivots is not None and motion.pivots.shape == (3, FOOT_SAMPLES + 1, 3)
    phases = np.arange(FOOT_SAMPLES) / FOOT_SAMPLES  # on the table's grid
    n = phases.size
    yaw0, yaw1 = 0.3, 0.3 + 0.15
    hx0, hz0, hx1, hz1 = (np.full(n, v) for v in (math.sin(yaw0), math.cos(yaw0), math.sin(yaw1), math.cos(yaw1)))
    scale = np.full(n, 1.05)
    sk = zombie.skeleton
    feet = foot_joints(sk)
    world = lambda hx, hz, p: np.stack([hz * p[:, 0] + hx * p[:, 1], -hx * p[:, 0] + hz * p[:, 1]], axis=1)
    for role, r in (("shamble", 1), ("run", 2)):
        weights = [np.zeros(n), np.zeros(n), np.zeros(n)]
        weights[r][:] = 1.0
        dx, dz = turn_about_planted_foot(motion, phases, weights, hx0, hz0, hx1, hz1, scale)
        # The truth, from the clip's own forward kinematics at those phases and the next sample.
        grid = np.arange(FOOT_SAMPLES + 1) / FOOT_SAMPLES
        pos = global_matrices(sk, sample_clip(sk, zombie.clip(role), grid))[:, feet][..., :3, 3]
        down = pos[..., 1] - pos[..., 1].min(axis=0) <= 0.03
        planted = down.any(axis=1)[:-1] & down.any(axis=1)[1:]
        pivot = (pos[:-1] * down[:-1, :, None]).sum(axis=1) / np.maximum(down[:-1].sum(axis=1), 1)[:, None]
        pivot = pivot[:, [0, 2]] * scale[0]
        after = world(hx1, hz1, pivot) + np.stack([dx, dz], axis=1)
        assert np.abs(after - world(hx0, hz0, pivot))[planted].max() < 1e-12, role
        assert np.abs(dx[planted]).max() > 0.005, role  # a real shift: the pivot is not the origin
        assert np.all(dx[~planted] == 0.0) and np.all(dz[~planted] == 0.0), role
    assert not planted.all()  # the run has its flight
