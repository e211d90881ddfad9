"""A round a newcomer can play (crowd.sim.rounds, crowd.sim.player, the AI's start_clear and alert_rate):
the horde starts at a distance and notices the player over time, its blows land at their impact on a
player still in reach, the survivor's swing sweeps what is in front of it, health comes back away from the
horde, and every round's length, kills and end are kept. Then the game as the headless demo plays it, on
llvmpipe: the scripted survivor outlasts one that stands still (`crowd-bench rounds` plays the full 10
seeds without GL; docs/BENCHMARKS.md has its figures)."""

from __future__ import annotations

import numpy as np
import pytest

from crowd.sim.ai import CrowdAI
from crowd.sim.config import ATTACK, CHASE, AIConfig
from crowd.sim.motion import motion_for
from crowd.sim.player import BLOW_DAMAGE, HEALTH, REGEN_DELAY, REGEN_RATE, Survivor
from crowd.anim.roles import bake_roles, match_roles

STEP = 1 / 60


@pytest.fixture(scope="module")
def motion(zombie):
    roles, _ = match_roles(zombie.clips)
    return motion_for(zombie, bake_roles(zombie, roles), roles)


@pytest.fixture(scope="module")
def survivor_motion():
    from bench.rounds_report import _cast
    from crowd.scene import Scene

    return _cast(Scene().with_overrides(town=False))[3]


def test_a_crowd_starts_with_the_horde_at_a_distance_at_its_own_density(motion):
    config = AIConfig()
    for agents in (1, 200, 5000):
        ai = CrowdAI(agents, 3, motion, config)
        d = np.hypot(ai.x - ai.player[0], ai.z - ai.player[1])
        assert d.min() >= config.start_clear, agents
        open_area = (2 * ai.half_extent) ** 2 - np.pi * config.start_clear ** 2  # the world less the clear disc
        assert open_area / agents == pytest.approx(config.area_per_agent, rel=1e-9), agents
    none = CrowdAI(200, 3, motion, AIConfig(start_clear=0.0))
    assert none.half_extent < CrowdAI(200, 3, motion, config).half_extent


def test_more_of_the_horde_notices_the_player_as_the_round_goes_on(motion):
    config = AIConfig(wander_speed=0.0, reaction_min=0.0, reaction_max=0.0)
    assert config.alert(0.0) == 0.0 and config.alert(10.0) == pytest.approx(10 * config.alert_rate)
    assert config.alert(1e6) == config.think_radius - config.notice_radius  # no further than every zombie thinks
    ai = CrowdAI(1, 1, motion, config)
    gap = config.notice_radius + 5.0
    ai.x[0], ai.z[0] = ai.player[0] + gap, ai.player[1]
    noticed = None
    for k in range(int(40 / STEP)):
        ai.step(STEP)
        ai.x[0], ai.z[0] = ai.player[0] + gap, ai.player[1]  # held where it stands (it would come closer once chasing)
        if ai.state[0] == CHASE:
            noticed = ai.time
            break
    assert noticed is not None and noticed == pytest.approx(5.0 / config.alert_rate, abs=2 * STEP)


@pytest.mark.parametrize("stays", [True, False])
def test_a_blow_lands_at_its_impact_on_a_player_still_in_reach(motion, stays):
    """A zombie starts its swing beside the player: the blow counts once, at the impact (half way), if the
    player is still within reach then; one who stepped away dodged it."""
    ai = CrowdAI(1, 2, motion, AIConfig(start_clear=0.0))
    ai.x[0], ai.z[0] = ai.player[0] + 1.0, ai.player[1]
    ai.state[0] = CHASE
    ai.step(STEP)
    assert ai.state[0] == ATTACK and ai.player_hits_taken == 0  # a swing begun is no blow yet
    if not stays:
        ai.player = ai.player + np.array([-3.0, 0.0])
    length = motion.duration["attack"]
    while ai.state[0] == ATTACK:
        before = ai.player_hits_taken
        ai.step(STEP)
        if ai.player_hits_taken > before:
            assert ai.time == pytest.approx(STEP + 0.5 * length, abs=1.5 * STEP)
    assert ai.player_hits_taken == (1 if stays else 0)


def test_the_swing_sweeps_every_zombie_in_front_within_reach(motion):
    ai = CrowdAI(6, 4, motion, AIConfig(start_clear=0.0))
    ai.player = np.zeros(2)
    ai.x[:], ai.z[:] = [1.0, 1.5, -1.0, 0.0, 3.0, 0.5], [0.5, -1.0, 0.5, 1.9, 0.0, 0.0]
    ai.state[5] = 5  # dead
    front = ai.alive_in_front((0.0, 0.0), 2.0, (1.0, 0.0))
    assert front.tolist() == [0, 1, 3]  # not behind (2), not out of reach (4), not the dead (5)


def test_health_comes_back_away_from_the_horde_and_each_round_is_kept(survivor_motion):
    s = Survivor(survivor_motion)
    s.hurt(3)
    assert s.health == HEALTH - 3 * BLOW_DAMAGE
    for _ in range(int(REGEN_DELAY / STEP) - 2):
        s.step(STEP)
    assert s.health == HEALTH - 3 * BLOW_DAMAGE  # not yet
    for _ in range(int(2.0 / STEP) + 4):
        s.step(STEP)
    assert s.health >= HEALTH - 3 * BLOW_DAMAGE + int(2.0 * REGEN_RATE) - 1
    s.kills = 4
    s.hurt(HEALTH)
    assert s.down and s.round_record()["end"] == "down"
    s.new_round((0.0, 0.0))
    assert s.history == [{"round": 1, "length_s": s.history[0]["length_s"], "kills": 4, "blows": 3 + HEALTH, "end": "down"}]
    assert s.round_record() == {"round": 2, "length_s": 0.0, "kills": 0, "blows": 0, "end": "playing"}


def test_rounds_without_gl_for_both_players(tmp_path):
    """`crowd-bench rounds`, cut short: its table and JSON, the still player down well before the scripted one."""
    import json

    from bench.cli import main

    out = tmp_path / "rounds.json"
    assert main(["rounds", "--seeds", "2", "--seconds", "60", "--json", str(out)]) == 0
    summary = json.loads(out.read_text())["summary"]
    assert summary["still"]["still_playing"] == 0 and summary["still"]["max_s"] < 55.0
    assert summary["scripted"]["min_s"] > summary["still"]["max_s"] + 10.0


def test_the_headless_game_on_llvmpipe_the_scripted_survivor_outlasts_one_standing_still(gl_context):
    """The pipeline as the headless demo runs it (default scene, the town, 200 zombies): the scripted
    survivor is still in its first round after 45 simulated seconds; with no script it stands still, and
    is down before 60 (the stats keep the round: its length, kills, blows and end)."""
    import dataclasses

    from crowd.gl import Offscreen
    from crowd.pipeline import CrowdPipeline
    from crowd.scene import Scene
    from crowd.stats import pipeline_stats

    config = Scene().pipeline_config()
    with Offscreen(gl_context, (32, 18)) as target:
        with CrowdPipeline(gl_context, config) as p:
            while p.ai.time < 45.0:
                p.frame(target.framebuffer, 1 / 20)
            rounds = pipeline_stats(p)["survivor"]["rounds"]
            assert len(rounds) == 1 and rounds[0]["end"] == "playing" and rounds[0]["kills"] > 0, rounds
        with CrowdPipeline(gl_context, dataclasses.replace(config, scripted_player=False)) as p:
            while p.survivor.rounds == 1 and p.survivor.round_time < 60.0:
                p.frame(target.framebuffer, 1 / 20)
            rounds = pipeline_stats(p)["survivor"]["rounds"]
    assert rounds[0]["end"] == "down" and 20.0 < rounds[0]["length_s"] < 60.0 and rounds[0]["kills"] == 0, rounds
    assert rounds[-1]["end"] == "playing" and rounds[-1]["round"] == 2
