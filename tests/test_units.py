"""Issue 18, point 3 (first part): characters brought to a person's size, measured from the skinned
rest pose, with ``model_scale`` (scene, command line) setting the factor instead."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import shared
from crowd.anim import reference
from crowd.asset.gltf import load_character
from crowd.asset.gltf_write import write_glb
from crowd.asset.units import HUMAN_HEIGHTS, TARGET_HEIGHT, scale_character, standing_height, to_crowd_units
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import PipelineConfig, PipelineError
from crowd.sim.config import AIConfig
from crowd.smoke import run_headless

SIZE = (320, 180)


def joint_positions(character, clip_index: int = 0) -> np.ndarray:
    sk = character.skeleton
    pose = reference.sample_clip(sk, character.clips[clip_index], np.linspace(0, 1, 7))
    return reference.global_matrices(sk, pose)[..., :3, 3]


def skinned_points(character) -> np.ndarray:
    sk = character.skeleton
    skin = reference.skinning_matrices(sk, reference.sample_clip(sk, character.clips[0], np.array([0.3])))
    body = next(m for m in character.meshes if m.lod == 0)
    return reference.skin_points(skin, body.positions, body.joints, body.weights)[0]


def test_the_zombie_is_left_as_it_is(zombie):
    assert HUMAN_HEIGHTS[0] < standing_height(zombie) < HUMAN_HEIGHTS[1]
    assert to_crowd_units(zombie) is zombie and not any("scaled" in w for w in zombie.warnings)


def test_scaling_moves_every_skinned_point_by_the_factor(zombie):
    giant = scale_character(zombie, 44.0)
    np.testing.assert_allclose(joint_positions(giant), joint_positions(zombie) * 44.0, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(skinned_points(giant), skinned_points(zombie) * 44.0, rtol=1e-5, atol=1e-4)
    assert standing_height(giant) == pytest.approx(standing_height(zombie) * 44.0, rel=1e-6)
    for name, prop in giant.props.items():
        np.testing.assert_allclose(prop.grip[:3, 3], zombie.props[name].grip[:3, 3] * 44.0)


def test_a_character_80_units_tall_is_brought_to_a_person_and_says_so(zombie):
    factor = 80.0 / standing_height(zombie)
    giant = scale_character(zombie, factor)
    fixed = to_crowd_units(giant)
    assert standing_height(fixed) == pytest.approx(TARGET_HEIGHT, rel=1e-6)
    assert any("stands 80 units tall" in w and f"to {TARGET_HEIGHT:g} m" in w for w in fixed.warnings)
    # Strides (metres per cycle) follow, so the AI's feet stay planted.
    for before, after in zip(zombie.clips, fixed.clips):
        if before.stride is not None:
            assert after.stride == pytest.approx(before.stride * TARGET_HEIGHT / standing_height(zombie), rel=1e-6)
    kept = to_crowd_units(giant, 1.0)  # model_scale 1: the file's own size, asked for
    assert standing_height(kept) == pytest.approx(80.0, rel=1e-6)  # float32 positions
    doubled = to_crowd_units(zombie, 2.0)
    assert standing_height(doubled) == pytest.approx(2 * standing_height(zombie), rel=1e-6)
    assert any("model_scale" in w for w in doubled.warnings)


def test_an_imported_giant_draws_like_the_zombie_and_a_bad_scale_is_refused(tmp_path, gl_context, zombie):
    """Written as a glb 80 units tall and loaded through the pipeline: the crowd looks as the zombie's
    does (within 20 % of covered pixels); with model_scale 1 it does not (the mutation this guards)."""
    path = tmp_path / "giant.glb"
    write_glb(scale_character(zombie, 80.0 / standing_height(zombie)), path)
    crowd = dict(agents=40, seed=4, shadows=False, weapons=False, ai=AIConfig(half_extent=4.0))
    background = run_headless(PipelineConfig(**{**crowd, "agents": 0}), 2, SIZE, ctx=gl_context)["_image"].astype(int)
    covered = {}
    for name, config in (("zombie", PipelineConfig(**crowd)), ("giant, auto", PipelineConfig(**crowd, model=path)),
                         ("giant, as authored", PipelineConfig(**crowd, model=path, model_scale=1.0))):
        image = run_headless(config, 2, SIZE, ctx=gl_context)["_image"].astype(int)
        covered[name] = float((np.abs(image - background).max(axis=2) > 30).mean())
    assert covered["zombie"] > 0.005
    assert covered["giant, auto"] == pytest.approx(covered["zombie"], rel=0.2)
    assert abs(covered["giant, as authored"] - covered["zombie"]) > 0.2 * covered["zombie"]
    with pytest.raises(PipelineError, match="model scale must be a factor from 1e-06 to 1e\\+06 or 'auto', got 0"):
        CrowdPipeline(gl_context, PipelineConfig(agents=1, model=path, model_scale=0))


def test_shared_rigged_simple_is_scaled_to_a_person():
    character = load_character(shared("RiggedSimple.glb"))
    assert standing_height(character) == pytest.approx(TARGET_HEIGHT, rel=1e-6)
    assert any("stands 9.15 units tall" in w for w in character.warnings)
    cesium = load_character(shared("CesiumMan.glb"))  # 1.5 m: as authored
    assert standing_height(cesium) == pytest.approx(1.5066, abs=1e-3) and not any("scaled" in w for w in cesium.warnings)


def test_a_character_modelled_around_its_centre_is_put_on_the_ground(zombie):
    from crowd.asset.units import lift_character, rest_extent

    sunk = lift_character(zombie, -0.93)  # the zombie, modelled around its middle
    assert rest_extent(sunk)[0] == pytest.approx(rest_extent(zombie)[0] - 0.93, abs=1e-9)
    fixed = to_crowd_units(sunk)
    assert rest_extent(fixed)[0] == pytest.approx(0.0, abs=1e-9)
    assert any("off the ground" in w for w in fixed.warnings)
    moved = rest_extent(fixed)[0] - rest_extent(zombie)[0]
    np.testing.assert_allclose(joint_positions(fixed), joint_positions(zombie) + [0.0, moved, 0.0], atol=1e-9)
    assert to_crowd_units(zombie) is zombie  # its soles sink 9 mm into the ground: within the tolerance


def test_shared_rigged_simple_stands_on_the_ground():
    from crowd.asset.units import rest_extent

    low, high = rest_extent(load_character(shared("RiggedSimple.glb")))
    assert low == pytest.approx(0.0, abs=1e-6) and high == pytest.approx(TARGET_HEIGHT, rel=1e-6)


def test_root_motion_is_taken_out_of_a_looping_walk_and_becomes_its_stride(zombie):
    """The zombie's shamble, exported as Mixamo would (the root travels a stride per cycle, no stride
    given): the travel comes out of the root keys as a line in time, the stride is that travel, and the
    pose is the in-place shamble again. One-shot clips keep their motion."""
    import dataclasses

    from crowd.asset.root_motion import take_out_root_motion

    shamble = zombie.clip("shamble")
    assert shamble.loop and shamble.stride
    root = int(np.flatnonzero(zombie.skeleton.parents < 0)[0])
    travel = np.array([0.2, 0.0, 1.0]) / np.linalg.norm([0.2, 0.0, 1.0]) * shamble.stride

    def travelling(channel):
        if channel.path != "translation" or channel.joint != root:
            return channel
        u = (channel.times - shamble.start) / shamble.duration
        return dataclasses.replace(channel, values=channel.values + u[:, None] * travel)

    exported = dataclasses.replace(shamble, channels=[travelling(c) for c in shamble.channels], stride=None)
    assert any(c.path == "translation" and c.joint == root for c in shamble.channels)
    death = zombie.clip("death")  # one-shot, and it travels (0.55 m): kept as it is
    character = dataclasses.replace(zombie, clips=[exported, death], warnings=[])
    fixed = take_out_root_motion(character)
    walk = fixed.clip("shamble")
    assert walk.stride == pytest.approx(shamble.stride, rel=1e-9)
    sk = zombie.skeleton
    phases = np.linspace(0.0, 1.0, 25)
    np.testing.assert_allclose(reference.sample_clip(sk, walk, phases).translation,
                               reference.sample_clip(sk, shamble, phases).translation, atol=1e-9)
    assert fixed.clip("death") is death
    assert [w for w in fixed.warnings if "root travels" in w and "'shamble'" in w]
    assert take_out_root_motion(zombie) is zombie  # the zombie's clips are in place already
