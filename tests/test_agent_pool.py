"""The crowd AI stepped by several processes (crowd.sim.agent_pool, issue 20): the same seed gives the
same crowd, bit for bit, whatever the worker count; the pool starts and stops with the crowd's size
and settings and leaves no process or shared memory behind; a worker that dies is one line."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from crowd.anim.roles import bake_roles, match_roles
from crowd.sim.ai import CrowdAI, PlayerScript
from crowd.sim.config import AIConfig, AIError
from crowd.sim.motion import motion_for
from crowd.sim.workers import MIN_RANGE

STEP = 1.0 / 30.0  # two substeps a step, as the headless loop steps
AGENTS = 6 * MIN_RANGE  # enough for six ranges


@pytest.fixture(scope="module")
def motion(zombie):
    roles, _ = match_roles(zombie.clips)
    baked = bake_roles(zombie, roles)
    return motion_for(zombie, baked, roles)


@pytest.fixture
def created_blocks(monkeypatch):
    """Names of the shared-memory blocks this test creates (other processes on the machine make their
    own, so /dev/shm as a whole says nothing)."""
    from crowd.sim import agent_pool

    names = []
    init = agent_pool.SharedArrays.__init__

    def recording(self, layout, name=None):
        init(self, layout, name)
        if name is None:
            names.append(self.name)

    monkeypatch.setattr(agent_pool.SharedArrays, "__init__", recording)
    return names


def _left_behind(names) -> list[str]:
    shm = Path("/dev/shm")
    return [n for n in names if (shm / n.lstrip("/")).exists()] if shm.is_dir() else []


def _state(ai: CrowdAI) -> dict:
    out = {name: getattr(ai, name).copy() for name in ai._names()}
    out["layers"] = ai.write_layers().copy()
    out["yaw"] = ai.instances().yaw
    out["hits"] = np.array([ai.player_hits_taken, ai.pair_builds, ai.substeps])
    return out


def _run(motion, workers: int, think_every: int, steps: int = 90, switch_to: int | None = None) -> dict:
    # A small world and short corpse times, so the player's strikes kill and the dead respawn (both draw
    # keyed random numbers), the crowd around the player from the start, and a focus point, as the
    # pipeline sets the camera.
    config = AIConfig(workers=workers, think_every=think_every, think_from=0, health=1, corpse_time=0.5,
                      area_per_agent=2.0, start_clear=0.0)
    ai = CrowdAI(AGENTS, 5, motion, config)
    try:
        script = PlayerScript(ai.half_extent * 0.3, strike_every=0.1)
        ai.focus = (np.array([ai.half_extent * 0.4, -ai.half_extent * 0.5]),)
        for step in range(steps):
            if step == steps // 2:  # new settings half-way (as the panel sets them): the same or another worker count
                ai.set_config(AIConfig(**{**config.__dict__, "workers": workers if switch_to is None else switch_to}))
            script.update(ai)
            ai.step(STEP)
        assert ai.check() == []
        assert ai.counts()["dead"] + ai.counts()["dying"] > 0 and ai.pair_builds > 2
        return _state(ai)
    finally:
        ai.close()


@pytest.mark.parametrize("think_every", [1, 8])
def test_the_same_seed_gives_the_same_crowd_for_any_worker_count(motion, think_every, created_blocks):
    alone = _run(motion, 1, think_every)
    for workers in (2, 3):
        other = _run(motion, workers, think_every)
        differ = [name for name in alone if not np.array_equal(alone[name], other[name])]
        assert not differ, f"{workers} workers: {differ} differ from one process"
    switched = _run(motion, 3, think_every, switch_to=1)  # workers stopped half-way, state moved back
    assert all(np.array_equal(alone[name], switched[name]) for name in alone)
    assert created_blocks and not _left_behind(created_blocks), "shared memory left behind"


def test_a_new_round_keeps_the_workers_and_is_the_crowd_a_fresh_start_gives(motion, created_blocks):
    """A new round's crowd takes the last crowd's worker processes (no restart: it froze the round's first
    frame), and steps exactly as a crowd of the same seed started afresh in one process."""
    config = AIConfig(workers=3, health=1, corpse_time=0.5, area_per_agent=2.0)
    last = CrowdAI(AGENTS, 5, motion, config)
    fresh = CrowdAI(AGENTS, 9, motion, AIConfig(**{**config.__dict__, "workers": 1}))
    try:
        for _ in range(4):
            last.step(STEP)
        pool = last._pool
        procs = list(pool._procs)
        crowd = CrowdAI(AGENTS, 9, motion, config)
        crowd.take_workers(last)
        last.close()
        assert crowd._pool is pool and last._pool is None and all(p.is_alive() for p in procs)
        for ai in (crowd, fresh):
            script = PlayerScript(ai.half_extent * 0.3, strike_every=0.1)
            for _ in range(40):
                script.update(ai)
                ai.step(STEP)
        assert crowd._pool is pool  # the same processes all along
        ours, theirs = _state(crowd), _state(fresh)
        assert [name for name in ours if not np.array_equal(ours[name], theirs[name])] == []
        crowd.close()
    finally:
        for ai in (last, fresh):
            ai.close()
    assert not any(p.is_alive() for p in procs)
    assert created_blocks and not _left_behind(created_blocks)


def test_the_pool_follows_the_crowd_size_and_releases_everything(motion, created_blocks):
    ai = CrowdAI(500, 2, motion, AIConfig(workers=3))
    try:
        ai.step(STEP)
        assert ai.ranges() == 1 and ai._pool is None  # a small crowd runs in this process: no workers
        first = ai.x[:500].copy()
        ai.resize(AGENTS)
        ai.step(STEP)
        assert ai.ranges() == 3 and ai._pool is not None
        procs = list(ai._pool._procs)
        assert all(p.is_alive() for p in procs)
        kept = ai.x[:500].copy()
        ai.resize(0)
        ai.step(STEP)
        ai.resize(AGENTS)
        ai.step(STEP)
        assert ai.check() == []
        ai.resize(200)
        ai.step(STEP)
        assert ai.check() == [] and not np.array_equal(kept, first)
    finally:
        ai.close()
    assert not any(p.is_alive() for p in procs)
    assert created_blocks and not _left_behind(created_blocks)


def test_a_worker_that_dies_is_one_line_not_a_hang(motion):
    ai = CrowdAI(AGENTS, 3, motion, AIConfig(workers=2))
    try:
        ai.step(STEP)
        ai._pool._procs[0].kill()
        ai._pool._procs[0].join()
        with pytest.raises(AIError, match=r"^AI worker 1 exited with code -9$"):
            ai.step(STEP)
        assert ai._pool is None  # the pool is gone; the next step starts a new one
        ai.step(STEP)
        assert ai.check() == []
        ai._pool.close()  # as an interrupt while waiting for the workers leaves it
        ai.step(STEP)
        assert ai.check() == [] and not ai._pool.closed
    finally:
        ai.close()


def test_keyed_draws_are_uniform_and_independent_of_who_draws(motion):
    ai = CrowdAI(10, 1, motion)
    ids = np.arange(200_000)
    draws = ai._draws(ids, 1, 2)
    assert draws.min() >= 0.0 and draws.max() < 1.0
    assert abs(draws.mean() - 0.5) < 0.005 and abs(np.corrcoef(draws[0], draws[1])[0, 1]) < 0.01
    np.testing.assert_array_equal(ai._draws(ids[7:9], 1, 2), draws[:, 7:9])  # an agent's numbers, whoever else draws
    ai.substeps += 1
    assert not np.array_equal(ai._draws(ids[:10], 1, 2), draws[:, :10])


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="no CPU affinity on this OS")
def test_zero_workers_means_one_per_core(motion):
    ai = CrowdAI(AGENTS, 1, motion, AIConfig(workers=0))
    try:
        assert ai.ranges() == min(len(os.sched_getaffinity(0)), 6)
    finally:
        ai.close()


@pytest.fixture(scope="module")
def mixed(zombie):
    """The zombie's and the brute's motions: a crowd of two characters, half each."""
    from crowd.asset.gltf import load_character

    out = []
    for character in (zombie, load_character("brute")):
        roles, _ = match_roles(character.clips)
        out.append(motion_for(character, bake_roles(character, roles), roles))
    return out


@pytest.mark.parametrize("think_every", [1, 8])
def test_a_mixed_cast_is_the_same_crowd_for_any_worker_count(mixed, think_every, created_blocks):
    """Each process steps its agents with their own character's motion (per-agent copies in the shared
    block), so a cast of two gives the same crowd, bit for bit, on one process and on three."""
    alone = _run(mixed, 1, think_every)
    other = _run(mixed, 3, think_every)
    differ = [name for name in alone if not np.array_equal(alone[name], other[name])]
    assert not differ, f"3 workers: {differ} differ from one process"
    assert set(np.unique(alone["kind"])) == {0, 1}
    assert created_blocks and not _left_behind(created_blocks), "shared memory left behind"


def test_a_crowd_in_the_town_is_the_same_for_any_worker_count(motion, created_blocks):
    """In the town the chasers steer by the flow field, made by the main process a few units of work a
    substep and published into the shared arrays when done: the same crowd, bit for bit, for 1 and 3
    processes, while the player runs through cells (fields made and published again and again), and the
    published field is the one made at once."""
    from crowd.asset.town import build_town
    from crowd.sim.obstacles import flow_field

    obstacles = build_town().obstacles()
    states, published = [], []
    for workers in (1, 3):
        ai = CrowdAI(AGENTS, 4, motion, AIConfig(workers=workers, notice_radius=30.0, forget_radius=40.0, area_per_agent=4.0), obstacles=obstacles)
        try:
            script = PlayerScript(12.0, strike_every=0.2)
            cells = set()
            for _ in range(60):
                script.update(ai)
                ai.step(STEP)
                cells.add(ai._flow_cell)
            assert ai.check() == [] and ai.counts()["chase"] > 0 and ai._flow_corner[2] == 1.0
            if workers > 1:  # the field is in the block the workers map, not made again in each of them
                assert ai._pool is not None and ai._block.arrays["_flow_steps"] is ai._flow_steps
            corner, step_i, step_j, usable = flow_field(obstacles, ai._flow_cell)
            assert np.array_equal(ai._flow_corner[:2], corner) and np.array_equal(ai._flow_usable, usable)
            assert np.array_equal(ai._flow_steps[0], step_i) and np.array_equal(ai._flow_steps[1], step_j)
            published.append(len(cells))
            states.append(_state(ai))
        finally:
            ai.close()
    assert published[0] > 3  # the player crossed cells: fields were made and published again
    assert [name for name in states[0] if not np.array_equal(states[0][name], states[1][name])] == []
    assert not _left_behind(created_blocks)
