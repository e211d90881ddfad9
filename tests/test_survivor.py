"""The survivor to play (issue 22, point 2): the built-in character, its controller (the clips play from
its speed and actions, its health and rounds), and its place in the pipeline as one more character."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crowd.anim import accuracy
from crowd.anim.bake import bake
from crowd.anim.foot_skate import joint_positions, measure, to_world
from crowd.asset.gltf import load_character
from crowd.asset.gltf_write import glb_bytes
from crowd.asset.model import foot_joints
from crowd.asset.survivor import ASSET_PATH, build_character
from crowd.frame import CLIP, MASK, PHASE, WEIGHT, validate_layers
from crowd.gl import Offscreen
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import CharacterSpec, PipelineConfig
from crowd.sim.config import AIConfig
from crowd.sim.player import HEALTH, HIT, NONE, ROLES, STRIKE, PlayerError, Survivor, survivor_motion


@pytest.fixture(scope="module")
def survivor_character():
    return load_character("survivor")


@pytest.fixture(scope="module")
def baked(survivor_character):
    return bake(survivor_character.skeleton, [survivor_character.clip(r) for r in ROLES])


@pytest.fixture
def survivor(survivor_character, baked):
    return Survivor(survivor_motion(survivor_character, baked), (0.0, 0.0))


def test_committed_glb_is_what_the_generator_writes():
    assert ASSET_PATH.read_bytes() == glb_bytes(build_character()), "assets/survivor.glb is stale: run python -m crowd.asset.survivor"


def test_it_has_the_clips_a_player_needs_and_a_bat(survivor_character):
    assert {c.name for c in survivor_character.clips} == set(ROLES)
    assert set(survivor_character.props) == {"bat"} and survivor_character.sockets == {"weapon_r": survivor_character.skeleton.index("hand_r_socket")}


@pytest.mark.parametrize("clip, sideways", [("run", 0.0), ("strafe_left", 1.0), ("strafe_right", -1.0)])
def test_its_locomotion_plants_its_feet(survivor_character, baked, clip, sideways):
    """Each locomotion clip, moved as fast as its stride says (forward, or sideways to its left or right),
    keeps its feet still in world space while they are down: under 1 cm of slide per metre."""
    c = survivor_character.clip(clip)
    rate, frames = 120.0, 300
    speed = c.stride / c.duration
    phase = np.mod(np.arange(frames) / rate / c.duration, 1.0)
    layers = np.zeros((frames, 1, 4), np.float32)
    layers[:, 0, CLIP] = [b.name for b in baked.clips].index(clip)
    layers[:, 0, PHASE] = phase
    layers[:, 0, WEIGHT] = 1.0
    layers[:, 0, MASK] = -1
    truth = accuracy.truth(survivor_character.skeleton, [survivor_character.clip(b.name) for b in baked.clips], layers)
    walked = speed * np.arange(frames) / rate
    ground = np.stack([sideways * walked, walked if not sideways else np.zeros(frames)], axis=1)
    feet = foot_joints(survivor_character.skeleton)
    world = to_world(joint_positions(truth, survivor_character.skeleton, feet), ground, 0.0)
    skate = measure(world, 1.0 / rate, float(walked[-1]), [survivor_character.skeleton.names[j] for j in feet])
    assert skate.worst_cm_per_m < 1.0, skate


def _play(s: Survivor, seconds: float, dt: float = 1 / 60):
    landed = []
    for _ in range(int(round(seconds / dt))):
        landed.append(s.step(dt))
    out = np.zeros((1, 4, 4), np.float32)
    return s.write_layers(out), landed


def test_its_clips_play_from_its_speed(survivor):
    """Standing: idle alone. Running forward: the run, its phase advancing by the speed over the run's
    stride. Side-stepping: the strafe clip of that side. Backing off: the run played backward."""
    m = survivor.motion
    layers, _ = _play(survivor, 0.5)
    assert layers[0, :3, WEIGHT].tolist() == [1.0, 0.0, 0.0]
    survivor.command((0.0, 1.0), face=(0.0, 1.0))  # forward: it faces +Z
    layers, _ = _play(survivor, 1.0)
    assert layers[0, 1, CLIP] == m.clip["run"] and layers[0, 1, WEIGHT] > 0.99
    assert np.hypot(*survivor.velocity) == pytest.approx(m.run_speed, rel=1e-3)
    before = survivor.phase
    survivor.step(0.01)
    assert (survivor.phase - before) % 1.0 == pytest.approx(m.run_speed / m.run_stride * 0.01, rel=1e-3)
    survivor.command((1.0, 0.0), face=(0.0, 1.0))  # toward +X: its left
    layers, _ = _play(survivor, 1.0)
    assert layers[0, 2, CLIP] == m.clip["strafe_left"] and layers[0, 2, WEIGHT] > 0.99
    survivor.command((-1.0, 0.0), face=(0.0, 1.0))
    layers, _ = _play(survivor, 1.0)
    assert layers[0, 2, CLIP] == m.clip["strafe_right"] and layers[0, 2, WEIGHT] > 0.99
    survivor.command((0.0, -1.0), face=(0.0, 1.0))  # backing off, still facing +Z
    _play(survivor, 1.0)
    before = survivor.phase
    survivor.step(0.01)
    assert 0.5 < (before - survivor.phase) % 1.0 * 100 / (0.5 * m.run_speed / m.run_stride) < 1.5  # backward, at half speed
    survivor.command((0.0, 0.0))
    layers, _ = _play(survivor, 1.0)
    assert layers[0, 0, WEIGHT] == 1.0


def test_a_swing_lands_once_and_blows_take_its_health(survivor):
    m = survivor.motion
    assert survivor.strike() and not survivor.strike()  # one swing at a time
    layers, landed = _play(survivor, m.duration["strike"] + 0.1)
    assert landed.count(True) == 1 and abs(landed.index(True) / 60 - m.impact * m.duration["strike"]) < 1 / 30
    assert survivor.action == NONE
    survivor.hurt(2)
    assert survivor.health == HEALTH - 20 and survivor.action == HIT and survivor.blows == 2
    layers = survivor.write_layers(np.zeros((1, 4, 4), np.float32))
    assert layers[0, 3, CLIP] == m.clip["hit"] and layers[0, 3, MASK] == m.upper_body_mask
    survivor.hurt(100)
    assert survivor.health == 0 and survivor.down and not survivor.strike()
    survivor.round_time = 12.5
    survivor.new_round((1.0, 2.0))
    assert survivor.health == HEALTH and survivor.kills == 0 and survivor.best_time == 12.5 and survivor.rounds == 2
    assert survivor.position.tolist() == [1.0, 2.0]


@pytest.mark.parametrize("bad", [(float("nan"), 0.0), (1.0,), "north", (float("inf"), 1.0)])
def test_bad_commands_are_one_line(survivor, bad):
    with pytest.raises(PlayerError) as info:
        survivor.command(bad)
    assert "\n" not in str(info.value)
    with pytest.raises(PlayerError):
        survivor.command((1.0, 0.0), face=(0.0, 0.0))
    with pytest.raises(PlayerError):
        survivor.walk_to(bad)


@pytest.mark.parametrize("dt", [float("nan"), -1.0, float("inf")])
def test_bad_frame_times_are_refused_and_huge_ones_clamped(survivor, dt):
    with pytest.raises(PlayerError):
        survivor.step(dt)
    survivor.command((1.0, 0.0))
    survivor.step(1e9)  # as the AI: a long frame is simulated as a short one
    assert np.all(np.isfinite(survivor.position)) and np.hypot(*survivor.position) < 2.0


def test_the_pipeline_draws_it_as_one_more_character_and_plays_the_game(gl_context):
    """One row after the crowd's, with its own bake and pieces; the zombies that reach it take its health,
    its swing kills, and at 0 health a new round starts with a new crowd, the best time kept."""
    config = PipelineConfig(agents=40, seed=3, characters=(CharacterSpec("zombie", 3), CharacterSpec("brute", 1)),
                            ai=AIConfig(half_extent=5.0, health=1, notice_radius=20.0, forget_radius=30.0), survivor=True)
    size = (320, 180)
    with Offscreen(gl_context, size) as target, CrowdPipeline(gl_context, config) as p:
        assert p.survivor is not None and p.counts == (30, 10, 1) and [m.name for m in p.cast] == ["zombie", "brute", "survivor"]
        p.camera = p.overview_camera(size[0] / size[1])
        s = p.survivor
        rounds, kills, seen_hurt = s.rounds, 0, False
        for frame in range(400):
            if frame % 20 == 0:
                s.strike()
            p.frame(target.framebuffer, 1 / 30)
            seen_hurt |= s.health < HEALTH
            kills = max(kills, s.kills)
            if s.rounds > rounds:
                break
        p.refresh_counts()
        assert seen_hurt and kills >= 1 and s.rounds == rounds + 1 and s.health == HEALTH and s.best_time > 0
        assert p.renderer.last["cast_visible"][-1] == 1  # drawn
        assert p.processor.nan_rows() == 0
        palette = p.processor.read_palette()
        assert np.all(np.isfinite(palette[-1]))
        # Its weapon is in its hand, read back like the zombies'.
        assert "survivor/bat" in p.weapons.names
        p.frame(target.framebuffer, 1 / 30)
        p.frame(target.framebuffer, 1 / 30)
        p.frame(target.framebuffer, 1 / 30)
        drawn_agents = p.weapons.drawn[0]
        assert p.rows - 1 in drawn_agents and p.weapon_error_mm() < 0.05


def test_without_a_survivor_the_player_is_a_point(gl_context):
    with Offscreen(gl_context, (64, 36)) as target, CrowdPipeline(gl_context, PipelineConfig(agents=10, survivor=False)) as p:
        p.frame(target.framebuffer, 1 / 30)
        assert p.survivor is None and p.counts == p.ai.cast == (10,) and [m.name for m in p.cast] == ["zombie"]
        assert p.gpu_bytes()["palette"] == p.processor.gpu_bytes()["palette"]
