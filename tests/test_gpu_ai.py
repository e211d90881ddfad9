"""The crowd AI on the GPU (crowd.sim.gpu) against its float64 reference, the numpy AI, on llvmpipe:
one substep from identical state per agent, 600 substeps in aggregate, the special cases, the grid
against brute force, and two runs bit for bit."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bench.ai_report import crowd_figures, near_threshold
from crowd.anim.roles import bake_roles, match_roles
from crowd.sim.ai import CrowdAI
from crowd.sim.config import ATTACK, CHASE, DEAD, DYING, HIT, WANDER, AIConfig
from crowd.sim.motion import motion_for

STEP = 1.0 / 60.0
CONFIG = AIConfig(think_every=1, workers=1, start_clear=0.0)  # the GPU has no think budget: every agent thinks every substep
# One substep from identical state: float32 state against float64, positions relative to an origin
# within 100 m (float32's step there: 7.6 µm).
TOLERANCE = {"x": 2e-5, "z": 2e-5, "vx": 2e-5, "vz": 2e-5, "hx": 2e-5, "hz": 2e-5, "phase": 2e-5, "tx": 2e-5, "tz": 2e-5,
             "state_time": 1e-5, "action_time": 1e-5, "cooldown": 1e-5, "aware": 1e-5, "pause": 1e-5}


@pytest.fixture(scope="module")
def motion(zombie):
    roles, _ = match_roles(zombie.clips)
    return motion_for(zombie, bake_roles(zombie, roles), roles)


@pytest.fixture
def gpu_ai(compute_context):
    from crowd.sim.gpu.ai import GpuCrowdAI

    made = []

    def make(ai):
        made.append(GpuCrowdAI(compute_context, ai))
        return made[-1]

    yield make
    for g in made:
        g.release()


def busy_crowd(motion, agents=1500, seed=3, steps=40, **config) -> CrowdAI:
    """A crowd some way into a fight: the player in its middle, so that agents chase, attack and are hit."""
    ai = CrowdAI(agents, seed, motion, dataclasses.replace(CONFIG, **config), origin=(40.0, -25.0))
    ai.player = ai.origin + np.array([2.0, 1.0])
    for k in range(steps):
        ai.step(STEP)
        if k % 10 == 5:
            ai.hit(np.flatnonzero(ai.alive())[:: 7])
    return ai


def one_substep_each(ai: CrowdAI, gpu_ai, warmup: int) -> tuple:
    """`ai` stepped `warmup` substeps, handed to the GPU, then one more substep on each path: (the GPU AI,
    its state, the agents not at a threshold)."""
    for _ in range(warmup):
        ai.step(STEP)
    g = gpu_ai(ai)
    ai.step(STEP)
    g.step(STEP)
    return g, g.download(), ~near_threshold(ai)


def test_one_substep_agrees_per_agent(motion, gpu_ai):
    ai = busy_crowd(motion)
    g = gpu_ai(ai)
    counts = ai.counts()
    assert counts["chase"] and counts["attack"] + counts["hit"] and counts["dying"] + counts["dead"], counts  # every branch runs
    ai.step(STEP)
    g.step(STEP)
    s = g.download()
    free = ~near_threshold(ai)
    for name in ("state", "action", "health"):
        differ = np.flatnonzero((getattr(ai, name) != s[name]) & free)
        assert differ.size == 0, (name, differ[:10])
    for name, tolerance in TOLERANCE.items():
        error = np.abs(getattr(ai, name) - s[name])[free]
        assert error.max() <= tolerance, (name, float(error.max()))
    assert np.array_equal(ai.tint, s["tint"]) and np.array_equal(ai.weapon, s["weapon"]) and np.array_equal(ai.head, s["head"])
    layers = g.layers()
    assert np.abs(layers - ai.layers())[free].max() <= 1e-4


def test_600_substeps_agree_in_aggregate(motion, gpu_ai):
    ai = CrowdAI(1200, 5, motion, CONFIG)
    g = gpu_ai(ai)
    for k in range(600):
        angle = k * STEP * 0.2
        ai.player = g.player = ai.origin + 12.0 * np.array([np.cos(angle), np.sin(angle)])
        if k % 54 == 53:  # a blow every 0.9 s on the nearest zombie in reach
            target = ai.nearest_alive(ai.player, 2.0)
            if target >= 0:
                ai.hit([target])
            g.strike_nearest(g.player, 2.0)
        ai.step(STEP)
        g.step(STEP)
    s = g.download()
    cpu = crowd_figures(ai.x, ai.z, ai.vx, ai.vz, ai.state, CONFIG.separation_radius)
    gpu = crowd_figures(s["x"], s["z"], s["vx"], s["vz"], s["state"], CONFIG.separation_radius)
    assert np.all(np.abs(cpu["counts"] - gpu["counts"]) <= 0.03 * ai.n + 5), (cpu["counts"], gpu["counts"])
    assert abs(cpu["speed"] - gpu["speed"]) <= 0.05 * cpu["speed"]
    assert abs(cpu["overlap"] - gpu["overlap"]) <= 0.25 * cpu["overlap"] + 1e-4
    assert np.all(np.abs(cpu["nearest"] - gpu["nearest"]) <= 0.05 * cpu["nearest"])
    half = g.half_extent
    assert np.all(np.abs(s["x"] - g.origin[0]) <= half) and np.all(np.abs(s["z"] - g.origin[1]) <= half)
    assert all(np.all(np.isfinite(s[k])) for k in ("x", "z", "vx", "vz", "hx", "hz", "phase"))


def test_two_runs_are_bit_identical(motion, gpu_ai):
    start = busy_crowd(motion, agents=3000, steps=20)
    runs = []
    for _ in range(2):
        g = gpu_ai(start)
        for k in range(120):
            g.player = start.player + 0.05 * k
            g.step(STEP if k % 7 else 0.1)
            if k % 30 == 0:
                g.strike_nearest(g.player, 2.0)
        runs.append(g.raw())
    for name in runs[0]:
        assert runs[0][name] == runs[1][name], name


def test_grid_holds_every_pair_in_order(motion, gpu_ai):
    """Every living agent once, each cell's agents in ascending order, and every pair closer than the
    cell size found in the 3 x 3 cells around either: against brute force."""
    ai = CrowdAI(2500, 9, motion, CONFIG)
    ai.x[:400] = ai.x[0]  # a pile-up: 400 agents on one point
    ai.z[:400] = ai.z[0]
    ai.state[400:450] = DEAD
    g = gpu_ai(ai)
    g.step(STEP)
    cell, first, order = g.grid.read(ai.n)
    s = g.download()
    live = np.flatnonzero(s["state"] < DYING)
    assert sorted(order[: live.size].tolist()) == live.tolist()
    side = g.grid.side
    for c in np.unique(cell[live]):
        members = order[first[c]:first[c + 1]]
        assert np.all(np.diff(members.astype(np.int64)) > 0)
        assert np.all(cell[members] == c)
    size = 2.0 * CONFIG.separation_radius
    pos = np.stack([s["x"], s["z"]], 1)[live]
    close = np.argwhere(((pos[:, None] - pos[None]) ** 2).sum(-1) < size * size)
    a, b = live[close[:, 0]], live[close[:, 1]]
    ca, cb = cell[a].astype(np.int64), cell[b].astype(np.int64)
    assert np.all((np.abs(ca % side - cb % side) <= 1) & (np.abs(ca // side - cb // side) <= 1))


def test_hit_death_and_respawn(motion, gpu_ai):
    ai = CrowdAI(300, 2, motion, dataclasses.replace(CONFIG, health=2, corpse_time=0.5))
    g = gpu_ai(ai)
    g.hit([5, 6, 6, -1, 10_000])
    s = g.download()
    assert s["state"][5] == HIT and s["state"][6] == HIT and s["health"][5] == 1 and s["aware"][5] >= s["reaction"][5]
    g.hit([5])
    s = g.download()
    assert s["state"][5] == DYING and g.read_counters()["kills"] == 1
    death = motion.duration["death"]
    steps = int((death + 0.5) / STEP) + 3
    before = g.steps
    for _ in range(steps):
        g.step(STEP)
    s = g.download()
    assert s["state"][5] == WANDER and s["health"][5] == 2 and s["spawned_step"][5] > before
    edge = g.half_extent - 0.5
    assert np.isclose(max(abs(s["x"][5] - g.origin[0]), abs(s["z"][5] - g.origin[1])), edge, atol=0.1)


def test_attacks_land_on_the_player(motion, gpu_ai):
    ai = CrowdAI(200, 4, motion, CONFIG)
    ai.x[:20] = ai.origin[0] + 0.5
    ai.z[:20] = ai.origin[1]
    ai.state[:20] = CHASE
    g = gpu_ai(ai)
    g.reset_counters()
    for _ in range(120):
        g.step(STEP)
    assert g.read_counters()["blows"] > 0
    assert np.count_nonzero(g.download()["state"] == ATTACK) + np.count_nonzero(g.download()["cooldown"] > 0) > 0


def test_a_mixed_cast_animates_each_character_with_its_clips(motion, gpu_ai):
    slower = dataclasses.replace(motion, walk_speed=motion.walk_speed * 0.5, run_speed=motion.run_speed * 0.5,
                                 clip={**motion.clip, "attack": -1}, pivots=None)
    ai = CrowdAI(900, 6, [motion, slower], CONFIG, shares=[2.0, 1.0])
    ai.player = ai.origin.copy()
    g, s, free = one_substep_each(ai, gpu_ai, 20)
    assert np.array_equal(s["kind"], ai.kind)
    assert np.abs(s["x"] - ai.x)[free].max() < 2e-5
    assert np.abs(g.layers() - ai.layers())[free].max() < 1e-4
    for _ in range(200):
        g.step(STEP)
    s = g.download()
    assert not np.any((s["kind"] == 1) & (s["state"] == ATTACK))  # the second character has no attack clip


def test_resize_keeps_each_characters_block(motion, gpu_ai):
    ai = CrowdAI(0, 8, [motion, motion], CONFIG, shares=[1.0, 1.0])
    g = gpu_ai(ai)
    g.step(STEP)
    for n in (100_000, 37, 0):
        ai.resize(n)
        was = {k: getattr(ai, k).copy() for k in ("tint", "kind", "weapon", "head")} if ai.n else None
        g.load(ai)
        g.step(STEP)
        g.store(ai)
        assert ai.n == n and g.n == n
        if n:
            assert all(np.array_equal(getattr(ai, k), v) for k, v in was.items())  # each character's agents kept their looks
    assert g.download()["x"].size == 0


def test_extreme_frames_and_a_pile_up_stay_finite(motion, gpu_ai):
    ai = CrowdAI(1000, 1, motion, dataclasses.replace(CONFIG, separation_stiffness=1e6))
    ai.x[:] = ai.x[0]
    ai.z[:] = ai.z[0]
    g = gpu_ai(ai)
    for dt in (0.0, 10.0, 1e-9, STEP, 0.25):
        g.step(dt)
    for _ in range(60):
        g.step(STEP)
    s = g.download()
    assert all(np.all(np.isfinite(s[k])) for k in ("x", "z", "vx", "vz", "hx", "hz", "phase"))
    pos = np.stack([s["x"], s["z"]], 1)
    assert len(np.unique(np.round(pos, 3), axis=0)) > 990  # spread apart
    with pytest.raises(ValueError, match="dt must be"):
        g.step(float("nan"))


def test_the_town_agrees_and_nobody_walks_into_a_building(motion, gpu_ai):
    from crowd.asset.town import build_town
    from crowd.sim.obstacles import CLEARANCE

    obstacles = build_town().obstacles()
    ai = CrowdAI(1500, 4, motion, CONFIG, obstacles=obstacles)
    ai.player = ai.origin + np.array([3.0, 2.0])
    g, s, free = one_substep_each(ai, gpu_ai, 60)
    assert np.abs(s["x"] - ai.x)[free].max() < 1e-4 and np.abs(s["z"] - ai.z)[free].max() < 1e-4
    assert np.count_nonzero((s["state"] != ai.state) & free) == 0
    for k in range(600):  # the player walks round the crossing; chasers follow the flow field round the corners
        angle = k * STEP * 0.25
        ai.player = g.player = ai.origin + 9.0 * np.array([np.cos(angle), np.sin(angle)])
        ai.step(STEP)
        g.step(STEP)
    s = g.download()
    for state, x, z in ((s["state"], s["x"], s["z"]), (ai.state, ai.x, ai.z)):
        inside = obstacles.distance(x, z) < CLEARANCE - 0.02
        assert np.count_nonzero(inside & (state < DYING)) == 0
    cpu, gpu = np.bincount(ai.state, minlength=6), np.bincount(s["state"], minlength=6)
    assert np.all(np.abs(cpu - gpu) <= 0.03 * ai.n + 5), (cpu, gpu)
    assert np.count_nonzero(s["state"] == CHASE) > 0


def test_a_resize_on_the_gpu_copies_each_characters_kept_block(motion, gpu_ai):
    ai = CrowdAI(3000, 5, [motion, motion], CONFIG, shares=[2.0, 1.0])
    g = gpu_ai(ai)
    for _ in range(30):
        g.step(STEP)
    was = g.download()
    for n in (5000, 1200, 0, 40):
        ai.resize(n)
        g.sent_bytes = 0
        g.resize_from(ai)
        now = g.download()
        assert g.n == n and g.sent_bytes == 0  # (the new agents spawned on the GPU)
        for (old, new, count) in ai.moved:
            for name in ("x", "phase", "state", "tint"):
                assert np.array_equal(now[name][new:new + count], was[name][old:old + count]), name
        g.step(STEP)
        was = g.download()


def test_a_pile_up_is_pushed_apart_as_the_numpy_ai_pushes_it(motion, gpu_ai):
    """300 agents standing in a 4 m disc among 4,000: past the cap of candidates a row of cells, the
    GPU's grid must hold the same candidates as the numpy twin's (its cells, in agent order)."""
    ai = CrowdAI(4000, 1, motion, CONFIG)
    rng = np.random.default_rng(0)
    k = 300
    radius, angle = 4.0 * np.sqrt(rng.uniform(0, 1, k)), rng.uniform(0, 2 * np.pi, k)
    ai.x[:k], ai.z[:k] = ai.origin[0] + radius * np.cos(angle), ai.origin[1] + radius * np.sin(angle)
    ai.vx[:] = ai.vz[:] = 0.0
    ai.tx[:], ai.tz[:], ai.pause[:] = ai.x, ai.z, 5.0
    ai.player = ai.origin + 500.0
    g = gpu_ai(ai)
    ai.step(STEP)
    g.step(STEP)
    s = g.download()
    assert np.hypot(ai.x - s["x"], ai.z - s["z"]).max() < 1e-4


def test_the_gpu_socket_list_takes_any_number_of_characters(motion, compute_context):
    """40 characters (past the 32 a bit mask would hold), only the 36th with impostors: its far agents
    are left out of the sockets' list, everyone else's armed agents are in it."""
    from crowd.draw.gpu_sockets import GpuSocketGather
    from crowd.sim.gpu.ai import GpuCrowdAI

    kinds = 40
    armed = dataclasses.replace(motion, weapon_count=1)
    ai = CrowdAI(800, 2, [armed] * kinds, dataclasses.replace(CONFIG, armed_share=1.0), shares=[1.0] * kinds)
    ctx = compute_context

    class Palette:  # three one-texel planes: the rows' values do not matter here, only who is listed
        layer_rows = 1

        def __init__(self):
            self.planes = [ctx.texture_array((1, 1, 1), 4, dtype="f4") for _ in range(3)]

        def bind_palette(self, unit, program):
            for i, plane in enumerate(self.planes):
                plane.use(unit + i)
            program["u_palette_rows"] = 1

    palette = Palette()
    far = [k == 35 for k in range(kinds)]
    with GpuCrowdAI(ctx, ai) as g, GpuSocketGather(ctx, np.zeros(kinds, np.int32), far) as gather:
        texel_base = ctx.buffer(np.zeros(ai.n, np.uint32).tobytes())
        eye = np.array([ai.origin[0], 1.7, ai.origin[1]])
        gather.gather(0, g.frame_output(), palette, texel_base, 0, eye, 3.0, None)
        ctx.finish()
        read, down, _ = gather.fetch(0)
        texel_base.release()
    for plane in palette.planes:
        plane.release()
    d2 = (ai.x - eye[0]) ** 2 + eye[1] ** 2 + (ai.z - eye[2]) ** 2
    expected = np.flatnonzero((ai.weapon >= 0) & ((ai.kind != 35) | (d2 <= 9.0)))
    assert np.array_equal(np.sort(np.concatenate([read.agents, down])), expected)
    assert np.count_nonzero(ai.kind[expected] == 35) < np.count_nonzero(ai.kind == 35)


@pytest.mark.parametrize("town", [False, True])
def test_a_new_crowd_is_spawned_on_the_gpu_as_the_numpy_ai_spawns_it(motion, compute_context, town):
    """A new crowd (and a resize's new agents) is a dispatch from the keyed draws, not its rows sent:
    every agent's looks, weapon, traits and start place as the float64 spawn gives them."""
    from crowd.asset.town import build_town
    from crowd.sim.gpu.ai import GpuCrowdAI

    armed, unarmed = dataclasses.replace(motion, head_count=3, weapon_count=4, weapon_first=2), dataclasses.replace(motion, weapon_count=0)
    config = dataclasses.replace(CONFIG, start_clear=12.0, armed_share=0.45, runner_share=0.3)
    obstacles = build_town().obstacles() if town else None
    ai = CrowdAI(6000, 21, [armed, unarmed], config, origin=(130.0, -75.0), shares=[2.0, 1.0], obstacles=obstacles)
    g = GpuCrowdAI(compute_context, ai, fresh=True)
    try:
        assert g.sent_bytes < 4096 * len(ai.motions)  # each character's tables, not the agents' rows (120 bytes an agent)
        for crowd in ("start", "resized"):
            s, n = g.download(), ai.n
            for name in ("state", "action", "health", "kind", "tint", "head", "weapon", "spawned_step", "runner", "phase"):
                assert np.array_equal(s[name], getattr(ai, name)), (crowd, name)
            for name, tolerance in (("hx", 1e-6), ("hz", 1e-6), ("scale", 1e-6), ("speed_factor", 1e-6), ("walk_top", 1e-5),
                                    ("chase_top", 1e-5), ("reaction", 1e-6), ("pause", 1e-6)):
                assert np.abs(s[name] - getattr(ai, name)).max() < tolerance, (crowd, name)
            # A start place differs only where float32 and float64 fall on two sides of a clearance.
            off = np.hypot(s["x"] - ai.x, s["z"] - ai.z)
            assert np.count_nonzero(off > 1e-3) <= n // 1000, (crowd, np.count_nonzero(off > 1e-3))
            new = (off <= 1e-3) & (ai.spawned_step == ai.steps)
            assert np.count_nonzero(new) > 1900 and np.all(np.hypot(s["x"] - ai.start_player[0], s["z"] - ai.start_player[1])[new] > 12.0 - 1e-3)
            if town:
                assert obstacles.distance(s["x"], s["z"]).min() > 0.3
            assert np.count_nonzero(ai.weapon >= 2) > 0.3 * ai.cast[0] and np.all(ai.weapon[ai.cast[0]:] == -1)
            for _ in range(5):
                ai.step(STEP)
                g.step(STEP)
            g.store(ai)
            ai.player = ai.origin + np.array([30.0, 0.0])
            ai.resize(9000)
            g.sent_bytes = 0
            g.resize_from(ai)
            assert g.sent_bytes == 0
    finally:
        g.release()


def test_a_character_wider_than_a_person_gets_room_by_its_footprint(motion, gpu_ai):
    """Issue 44: bats 3.2 m across kept only the setting's 0.75 m apart. A pair keeps the mean of its two
    characters' radii (the setting, times footprint / PERSON_FOOTPRINT where that is over 1), on the numpy
    AI and on its GPU twin alike; the built-in characters stand within a person's footprint."""
    from crowd.sim.separation import PERSON_FOOTPRINT, kind_radii

    assert motion.footprint <= PERSON_FOOTPRINT
    wide = dataclasses.replace(motion, footprint=1.6)  # a 3.2 m wingspan
    radii = kind_radii(CONFIG.separation_radius, [motion, wide])
    assert radii[0] == CONFIG.separation_radius and radii[1] == pytest.approx(CONFIG.separation_radius * 1.6 / PERSON_FOOTPRINT)
    config = dataclasses.replace(CONFIG, half_extent=14.0, wander_speed=0.0, notice_radius=0.01)
    ai = CrowdAI(240, 4, [motion, wide], config, shares=(0.5, 0.5))
    ai.x[:] = ai.origin[0] + np.linspace(-1.0, 1.0, ai.n)  # piled up on a line: separation spreads them
    ai.z[:] = ai.origin[1] + np.linspace(0.5, -0.5, ai.n)
    ai.player = ai.origin + 1e4
    g = gpu_ai(ai)
    for _ in range(900):
        ai.step(STEP)
        g.step(STEP)
    s = g.download()
    for x, z in ((ai.x, ai.z), (s["x"], s["z"])):
        pos = np.stack([x, z], 1)
        d = np.sqrt(((pos[:, None] - pos[None]) ** 2).sum(-1))
        np.fill_diagonal(d, np.inf)
        kind = ai.kind
        narrow_narrow = np.median(d[np.ix_(kind == 0, kind == 0)].min(1))
        wide_wide = np.median(d[np.ix_(kind == 1, kind == 1)].min(1))
        # Settled: each kind's median nearest neighbour of its own kind near its own radius, the wide far wider.
        assert 0.8 * radii[0] <= narrow_narrow <= 1.6 * radii[0], narrow_narrow
        assert 0.8 * radii[1] <= wide_wide, wide_wide
        assert wide_wide > 1.8 * narrow_narrow
