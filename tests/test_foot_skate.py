"""Foot skate (crowd.anim.foot_skate, issue 21 point 1): a clip built to slide by a known amount is
measured within 5 %, through the GPU processor and through the float64 reference; a planted foot
measures no slide; bad input is one line."""

from __future__ import annotations

import numpy as np
import pytest

from crowd.anim import accuracy
from crowd.anim.bake import bake
from crowd.anim.foot_skate import CONTACT_M, SkateError, foot_joints, joint_positions, measure, to_world
from crowd.asset.model import Channel, Clip, Skeleton
from crowd.frame import CLIP, PHASE, WEIGHT, empty_layers

SPEED = 1.0  # m/s the agent walks
RATE = 240.0  # frames a second measured
LIFT = 1.0 / 15.0  # seconds the foot takes to rise 10 cm (and to come down): key times on the 30 fps bake's grid
STANCE = 0.6


def _sliding_walk(slip: float) -> tuple[Skeleton, Clip, float]:
    """A hip and a foot. The foot's keys (LINEAR translation, a 1 s loop) move it backward at
    SPEED - slip whenever it is low (stance, lift and drop) and forward high up, so an agent walking at
    SPEED sees its foot slide forward at `slip` m/s whenever it is within 3 cm of the ground: 0.6 s of
    stance and, of each 10 cm rise and fall, the 3 cm nearest the ground (0.3 of LIFT each). Returns the
    skeleton, the clip and the slide expected in cm per metre walked."""
    u = SPEED - slip
    z0 = 0.3
    times = np.array([0.0, STANCE, STANCE + LIFT, 1.0 - LIFT, 1.0])
    # Back at u through stance and lift, forward high up, back at u again while coming down to z0.
    values = np.array([[0.0, 0.0, z0], [0.0, 0.0, z0 - u * STANCE], [0.0, 0.1, z0 - u * (STANCE + LIFT)],
                       [0.0, 0.1, z0 + u * LIFT], [0.0, 0.0, z0]])
    skeleton = Skeleton(("hips", "foot_l"), np.array([-1, 0], np.int32), np.zeros((2, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (2, 1)),
                        np.ones((2, 3)), np.tile(np.eye(4), (2, 1, 1)))
    clip = Clip("slide", [Channel(1, "translation", "LINEAR", times, values)], 0.0, 1.0, True)
    contact_s = STANCE + 2 * CONTACT_M / 0.1 * LIFT
    return skeleton, clip, 100.0 * slip * contact_s / SPEED


def _walk(skeleton, palette_or_truth, frames):
    t = np.arange(frames) / RATE
    ground = np.stack([np.zeros(frames), SPEED * t], axis=1)
    world = to_world(joint_positions(palette_or_truth, skeleton, foot_joints(skeleton)), ground, 0.0)
    return measure(world, 1.0 / RATE, SPEED * t[-1], ["foot_l"])


@pytest.mark.parametrize("slip", [0.05, 0.2])
def test_a_clip_built_to_slide_is_measured_within_5_percent(gl_context, slip):
    skeleton, clip, expected = _sliding_walk(slip)
    frames = int(4 * RATE)
    layers = empty_layers(frames, 1)
    layers[:, 0, CLIP] = 0
    layers[:, 0, PHASE] = np.mod(np.arange(frames) / RATE, 1.0)
    layers[:, 0, WEIGHT] = 1.0
    baked = bake(skeleton, [clip])
    for source in (accuracy.gpu_palette(gl_context, baked, layers), accuracy.truth(skeleton, [clip], layers)):
        skate = _walk(skeleton, source, frames)
        assert skate.slide_cm_per_m == pytest.approx(expected, rel=0.05), (skate, expected)
        assert skate.contact_share == pytest.approx((STANCE + 2 * CONTACT_M / 0.1 * LIFT), rel=0.05)
        # Every contact step is at the slip speed: over the threshold at 20 cm/s, under it at 5 cm/s.
        assert skate.share_over == (1.0 if slip > 0.1 else 0.0)


def test_a_planted_foot_does_not_slide(gl_context):
    skeleton, clip, expected = _sliding_walk(0.0)
    assert expected == 0.0
    frames = int(2 * RATE)
    layers = empty_layers(frames, 1)
    layers[:, 0, CLIP] = 0
    layers[:, 0, PHASE] = np.mod(np.arange(frames) / RATE, 1.0)
    layers[:, 0, WEIGHT] = 1.0
    skate = _walk(skeleton, accuracy.gpu_palette(gl_context, bake(skeleton, [clip]), layers), frames)
    assert skate.slide_cm_per_m < 0.05 and skate.share_over == 0.0  # float32 palette rounding only


def test_the_zombie_has_feet_and_toes(zombie):
    names = [zombie.skeleton.names[j] for j in foot_joints(zombie.skeleton)]
    assert names == ["foot_l", "foot_r", "toe_l", "toe_r"]


@pytest.mark.parametrize("world, dt, walked, message", [
    (np.zeros((1, 1, 3)), 0.01, 1.0, "frames >= 2"),
    (np.full((3, 1, 3), np.nan), 0.01, 1.0, "not finite"),
    (np.zeros((3, 1, 3)), 0.0, 1.0, "dt > 0"),
    (np.zeros((3, 1, 3)), 0.01, -1.0, "distance >= 0"),
])
def test_bad_input_is_one_line(world, dt, walked, message):
    with pytest.raises(SkateError, match=message) as info:
        measure(world, dt, walked, ["foot_l"])
    assert "\n" not in str(info.value)


def test_standing_still_reports_no_slide_per_metre_but_a_speed():
    frames = 11
    world = np.zeros((frames, 1, 3))
    world[:, 0, 0] = np.linspace(0.0, 0.01, frames)  # 1 cm over 0.1 s while in contact
    skate = measure(world, 0.01, 0.0, ["foot_l"])
    assert np.isnan(skate.slide_cm_per_m) and skate.slide_cm_per_s == pytest.approx(10.0)


@pytest.mark.parametrize("foot_lock, ai_path", [(False, "cpu"), (True, "cpu"), (True, "gpu")])
def test_the_running_crowd_s_feet_come_back_on_the_read_back_as_the_reference_puts_them(gl_context, foot_lock, ai_path):
    """The stats' foot_skate: the sampled agents' feet, read back with the sockets (never waited for),
    are those of the frame they were read from, within 1 mm: where the float64 reference puts them for
    that frame's layers and transforms, and with the foot lock (whose state the reference does not
    follow through a crowd) where that frame's palette, read at once, put them; the summary is finite."""
    from crowd.gl import Offscreen
    from crowd.pipeline import CrowdPipeline
    from crowd.pipeline_config import PipelineConfig

    with Offscreen(gl_context, (160, 90)) as target, CrowdPipeline(gl_context, PipelineConfig(agents=200, foot_lock=foot_lock, ai_path=ai_path)) as p:
        if foot_lock and p.processor.legs is None:
            pytest.skip("the foot lock runs on the compute path (GL 4.3)")
        assert p.ai_path == ai_path
        kept = {}
        for f in range(90):
            p.frame(target.framebuffer, 1.0 / 30.0)
            ai = p.ai if p.gpu_crowd is None else p.gpu_crowd.store()  # (a crowd on the GPU read back whole: a test)
            instances = ai.instances()  # the frame's own: nothing moves after its AI step
            palette = p.processor.read_palette() if foot_lock else None
            kept[f] = (p.layers.copy(), instances.position[:, [0, 2]].copy(), instances.yaw.copy(), instances.scale.copy(), palette)
        monitor = p.foot_skate
        clips = [p.character.clip(c.name) for c in p.bake.clips]
        checked = 0
        for agent, track in monitor.tracks().items():
            frame, _, ground, world = track[-1]
            layers, positions, yaw, scale, palette = kept[frame]
            if palette is None:
                matrices = accuracy.truth(p.character.skeleton, clips, layers[agent][None], p.processor.masks[0])
            else:
                matrices = palette[agent][None]
            model = joint_positions(matrices, p.character.skeleton, monitor.feet)
            expected = to_world(model, positions[agent][None], yaw[agent], float(scale[agent]))[0]
            np.testing.assert_allclose(ground, positions[agent])
            assert np.abs(world - expected).max() < 1e-3, (agent, frame)
            checked += 1
        assert checked >= 10 and p.readback_stalls == 0
        summary = monitor.summary()
        assert summary is not None and summary["agents"] >= 1
        assert all(np.isfinite(summary[k]) and summary[k] >= 0 for k in ("slide_cm_per_m", "worst_cm_per_m", "share_over"))


def _zombie_walk(zombie, speed: float, seconds: float = 3.2, rate: float = 120.0, motion=None):
    """The float64 reference's foot skate of a character (the built-in zombie) walking straight at
    `speed`, animated as the AI animates it (with `motion`, or the character's own)."""
    from crowd.anim.roles import bake_roles, match_roles
    from crowd.sim.locomotion import locomotion_layers
    from crowd.sim.motion import motion_for

    roles, _ = match_roles(zombie.clips)
    baked = bake_roles(zombie, roles)
    motion = motion or motion_for(zombie, baked, roles)
    frames = int(seconds * rate)
    layers, walked = locomotion_layers(motion, speed, frames, 1.0 / rate)
    truth = accuracy.truth(zombie.skeleton, [zombie.clip(c.name) for c in baked.clips], layers)
    feet = foot_joints(zombie.skeleton)
    world = to_world(joint_positions(truth, zombie.skeleton, feet), np.stack([np.zeros(frames), walked], axis=1), 0.0)
    return motion, layers, measure(world, 1.0 / rate, float(walked[-1]), [zombie.skeleton.names[j] for j in feet])


def test_the_built_in_walk_and_run_plant_their_feet(zombie):
    """Their legs are solved for feet that stand still in world space while low (crowd.asset.planted_feet,
    "Planted feet"): keyed angles had slid 33 cm (walk) and 4.4 cm (run) per metre. Measured: 0.39 and
    0.56 cm/m for the worst foot joint, the rest being the 30 fps keys' interpolation."""
    motion, _, _ = _zombie_walk(zombie, 0.0, seconds=0.1)
    for speed in (motion.walk_speed, motion.run_speed):
        skate = _zombie_walk(zombie, speed)[2]
        assert skate.worst_cm_per_m < 1.0, (speed, skate)


def test_a_slow_walk_is_the_walk_played_slower(zombie):
    """Between the walk's slowest playback and its own speed the walk plays alone, at speed over its
    stride, so its planted feet keep pace; below that idle fades in at that slowest rate."""
    motion, _, _ = _zombie_walk(zombie, 0.0, seconds=0.1)
    slowest = motion.walk_slowest * motion.walk_speed
    assert 0.25 <= motion.walk_slowest < 1.0
    for speed in (slowest * 1.01, 0.5 * (slowest + motion.walk_speed)):
        _, layers, skate = _zombie_walk(zombie, speed)
        assert layers[0, :3, WEIGHT].tolist() == [0.0, 1.0, 0.0]
        assert layers[1, 0, PHASE] - layers[0, 0, PHASE] == pytest.approx(speed / motion.walk_stride / 120.0, rel=1e-5)
        assert skate.worst_cm_per_m < 1.0, (speed, skate)
    _, layers, _ = _zombie_walk(zombie, 0.5 * slowest, seconds=0.1)
    assert layers[0, :3, WEIGHT].tolist() == pytest.approx([0.5, 0.5, 0.0])
    assert layers[1, 0, PHASE] - layers[0, 0, PHASE] == pytest.approx(slowest / motion.walk_stride / 120.0, rel=1e-5)


def test_a_bigger_zombie_takes_longer_strides(zombie):
    """Agents are drawn at their own size, and their strides with them: the phase's rate divides by the
    scaled stride (a 1.08 zombie at the same speed steps 1.08 times slower)."""
    from crowd.sim.locomotion import phase_rate

    motion, _, _ = _zombie_walk(zombie, 0.0, seconds=0.1)
    speed, walk = np.array([motion.walk_speed]), np.array([motion.walk_speed])
    plain = phase_rate(motion, speed, walk, np.zeros(1))
    assert phase_rate(motion, speed, walk, np.zeros(1), np.array([1.08])) == pytest.approx(plain / 1.08)


def test_a_crowd_walking_straight_does_not_slide(zombie):
    """crowd-bench skate --crowd: a wandering crowd's slide filed by what each agent did. The cases add
    up to the total, and frames of straight walking slide well under 1 cm/m (turns and pushes are what is
    left, docs/ACCURACY.md)."""
    from bench.skate_report import CROWD_CASES, crowd_breakdown
    from crowd.anim.roles import bake_roles, match_roles
    from crowd.sim.motion import motion_for

    roles, _ = match_roles(zombie.clips)
    baked = bake_roles(zombie, roles)
    report = crowd_breakdown(zombie, baked, motion_for(zombie, baked, roles), agents=120, steps=90, sample=12)
    cases = report["cases"]
    assert list(cases) == list(CROWD_CASES) and report["walked_m"] > 5.0
    assert sum(c["cm_per_m"] for c in cases.values()) == pytest.approx(report["total_cm_per_m"], abs=1e-3)
    straight = cases["walks straight"]
    assert straight["frames"] > 100 and straight["cm_per_m"] < 0.5, report


def test_a_stride_measured_from_the_feet_is_the_stride_they_walk(zombie):
    """stride_from_feet: the stride that leaves the least slide per metre. On the built-in clips, whose
    feet are planted by construction, it finds the strides they were built with."""
    from crowd.sim.motion import stride_from_feet

    for name in ("shamble", "run"):
        clip = zombie.clip(name)
        assert stride_from_feet(zombie, clip) == pytest.approx(clip.stride, rel=0.005), name


def test_an_imported_walk_without_a_stride_gets_one_from_its_feet():
    """A real file's in-place walk and run (no stride in the file): measured from their feet instead of
    the 1 m/s and 3 m/s guesses, they slide less (Quaternius' zombie: walk 38.9 -> 35.0 cm/m, run 20.9 ->
    5.9 on llvmpipe), and the AI says where the strides came from."""
    from conftest import shared
    from crowd.anim.roles import bake_roles, match_roles
    from crowd.asset.gltf import load_character
    from crowd.sim.motion import DEFAULT_RUN_SPEED, DEFAULT_WALK_SPEED, Motion, motion_for

    character = load_character(shared("Quaternius_Zombie_Basic.gltf"))
    roles, _ = match_roles(character.clips)
    baked = bake_roles(character, roles)
    measured = motion_for(character, baked, roles)
    assert sum("measured from its planted feet" in note for note in measured.notes) == 2
    guessed = Motion.from_bake(baked, roles, {})
    assert guessed.walk_speed == pytest.approx(DEFAULT_WALK_SPEED) and guessed.run_speed == pytest.approx(DEFAULT_RUN_SPEED)
    for role in ("walk", "run"):
        at = lambda m: _zombie_walk(character, getattr(m, f"{role}_speed"), motion=m)[2].slide_cm_per_m
        assert at(measured) < at(guessed), role
