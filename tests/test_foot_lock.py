"""The foot lock (crowd.anim.foot_lock, issue 21 point 2): the leg solver reaches what it is asked to;
the GPU lock and its float64 twin take the same decisions and give the same legs, frame by frame from
the same state; a turning walk stops sliding; a foot held too far steps; an agent whose legs need no
correction gets the unlocked palette bit for bit; bad input is one line; the buffers come and go
with the agents."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from crowd import transforms as tf
from crowd.anim import foot_lock as fl
from crowd.anim.foot_skate import foot_joints, joint_positions, measure, to_world
from crowd.anim.processor import AnimationProcessor
from crowd.anim.palette_reference import reference_palette
from crowd.anim.processor_inputs import ProcessorError
from crowd.anim.roles import bake_roles, match_roles
from crowd.asset.model import Skeleton
from crowd.asset.pose import rest_pose
from crowd.frame import CLIP, MASK, PHASE, WEIGHT, empty_layers

DT = 1.0 / 60.0


@pytest.fixture(scope="module")
def walker(zombie):
    roles, _ = match_roles(zombie.clips, {})
    bake = bake_roles(zombie, roles, 30.0, "f32", 0.5)
    return zombie, bake, fl.bake_legs(zombie.skeleton, bake), roles


def _compute(gl_context):
    if gl_context.version_code < 430:
        pytest.skip("the foot lock runs on the compute path (GL 4.3)")


def _skeleton(names, parents, positions) -> Skeleton:
    parents = np.asarray(parents, np.int32)
    pos = np.asarray(positions, np.float64)
    local = np.array([pos[i] - (pos[p] if p >= 0 else 0.0) for i, p in enumerate(parents)])
    n = len(names)
    bind = np.tile(np.eye(4), (n, 1, 1))
    bind[:, :3, 3] = pos
    return Skeleton(tuple(names), parents, local, np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)), np.ones((n, 3)), np.linalg.inv(bind))


def test_the_zombies_legs_are_found_with_their_toes(walker):
    character, _, legs, _ = walker
    names = character.skeleton.names
    assert legs.names == ("foot_l", "foot_r")
    for (hip_parent, hip, knee, ankle), toe in zip(legs.joints, legs.toe):
        assert names[knee].startswith("shin") and names[hip].startswith("thigh") and names[hip_parent] == "hips"
        assert names[toe].startswith("toe")
    # The lowest heights are the clips' (the bind pose stands 5 mm higher).
    assert np.all(legs.lowest[:, 0] < 0.09) and np.all(legs.lowest[:, 1] < 0.025)


def test_legs_that_share_joints_or_stand_on_nothing_are_left_out():
    # A foot helper under a foot, a second "foot" on the same shin, an arm named "football", a foot with no hip.
    names = ["hips", "thigh", "shin", "foot", "foot_twist", "foot_ik", "football", "ankle_stub"]
    parents = [-1, 0, 1, 2, 2, 3, 0, -1]
    pos = [(0, 1, 0), (0.1, 0.9, 0), (0.1, 0.5, 0), (0.1, 0.1, 0), (0.1, 0.1, 0.01), (0.1, 0.1, 0.02), (0.5, 1.4, 0), (0, 0, 0)]
    legs = fl.find_legs(_skeleton(names, parents, pos))
    assert len(legs) == 1 and legs.names[0] in ("foot", "foot_twist")
    assert len(fl.find_legs(_skeleton(["root", "spine"], [-1, 0], [(0, 1, 0), (0, 1.5, 0)]))) == 0


def _leg(rng, n):
    """n random legs: hip at the origin's parent frame turned at random, bones 0.3 to 0.5 m, knees bent."""
    parent_rot = tf.quat_to_mat3(tf.quat_normalize(rng.normal(size=(n, 4))))
    hip = np.tile(np.eye(4), (n, 1, 1))
    hip[:, :3, :3] = tf.quat_to_mat3(tf.quat_normalize(rng.normal(size=(n, 4))))
    hip[:, :3, 3] = rng.normal(0, 0.2, (n, 3))
    knee_local = np.tile(np.eye(4), (n, 1, 1))
    knee_local[:, :3, :3] = tf.quat_to_mat3(tf.quat_normalize(rng.normal(size=(n, 4))))
    knee_local[:, :3, 3] = rng.uniform(0.3, 0.5, (n, 1)) * np.array([0.0, -1.0, 0.0])
    ankle_local = np.tile(np.eye(4), (n, 1, 1))
    ankle_local[:, :3, :3] = tf.quat_to_mat3(tf.quat_normalize(rng.normal(size=(n, 4))))
    ankle_local[:, :3, 3] = rng.uniform(0.3, 0.5, (n, 1)) * np.array([0.0, -1.0, 0.0])
    return parent_rot, hip, hip @ knee_local, hip @ knee_local @ ankle_local


def _apply(parent_rot, hip, knee, ankle, q):
    """The leg's new globals after solve_leg's rotations pre-multiply the locals' linear parts."""
    def local(child, parent):
        return np.linalg.inv(parent) @ child

    parent = np.tile(np.eye(4), (len(hip), 1, 1))
    parent[:, :3, :3] = parent_rot
    l_hip, l_knee, l_ankle = local(hip, parent), local(knee, hip), local(ankle, knee)
    for l, r in zip((l_hip, l_knee, l_ankle), q):
        l[:, :3, :3] = r @ l[:, :3, :3]
    g_hip = parent @ l_hip
    g_knee = g_hip @ l_knee
    return g_hip, g_knee, g_knee @ l_ankle


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), reach=st.floats(0.05, 0.98), twist=st.floats(-1.2, 1.2))
def test_the_leg_reaches_its_target_keeps_its_bones_and_turns_its_foot(seed, reach, twist):
    rng = np.random.default_rng(seed)
    parent_rot, hip, knee, ankle = _leg(rng, 8)
    thigh = np.linalg.norm(knee[:, :3, 3] - hip[:, :3, 3], axis=1)
    shin = np.linalg.norm(ankle[:, :3, 3] - knee[:, :3, 3], axis=1)
    low, high = np.abs(thigh - shin), thigh + shin
    direction = tf.quat_to_mat3(tf.quat_normalize(rng.normal(size=(8, 4))))[:, :, 0]
    target = hip[:, :3, 3] + direction * (low + reach * (high - low))[:, None]
    q = fl.solve_leg(parent_rot, hip, knee, ankle, target, np.full(8, twist))
    g_hip, g_knee, g_ankle = _apply(parent_rot, hip, knee, ankle, q)
    inside = (reach > 0.02) & (np.linalg.norm(target - hip[:, :3, 3], axis=1) > low + 1e-4 * high)
    assert np.all(np.linalg.norm(g_ankle[:, :3, 3] - target, axis=1)[inside] < 1e-9)
    assert np.allclose(np.linalg.norm(g_knee[:, :3, 3] - g_hip[:, :3, 3], axis=1), thigh, atol=1e-12)
    assert np.allclose(np.linalg.norm(g_ankle[:, :3, 3] - g_knee[:, :3, 3], axis=1), shin, atol=1e-12)
    assert np.allclose(g_hip[:, :3, 3], hip[:, :3, 3], atol=1e-12)  # the hip stays where it is
    want = fl._yaw_rotation(np.full(8, twist)) @ ankle[:, :3, :3]
    assert np.abs(g_ankle[:, :3, :3] - want).max() < 1e-9  # the foot keeps its orientation, turned about +Y


def test_a_target_out_of_reach_straightens_the_leg_toward_it():
    rng = np.random.default_rng(3)
    parent_rot, hip, knee, ankle = _leg(rng, 16)
    h = hip[:, :3, 3]
    direction = np.array([0.3, -1.0, 0.2]) / np.linalg.norm([0.3, -1.0, 0.2])
    target = h + 2.0 * direction
    g_hip, g_knee, g_ankle = _apply(parent_rot, hip, knee, ankle, fl.solve_leg(parent_rot, hip, knee, ankle, target, np.zeros(16)))
    reach = np.linalg.norm(g_ankle[:, :3, 3] - h, axis=1)
    full = np.linalg.norm(knee[:, :3, 3] - h, axis=1) + np.linalg.norm(ankle[:, :3, 3] - knee[:, :3, 3], axis=1)
    assert np.all(reach > full * (1 - 2e-5))
    assert np.allclose((g_ankle[:, :3, 3] - h) / reach[:, None], direction, atol=1e-6)


def test_no_correction_turns_nothing():
    rng = np.random.default_rng(5)
    parent_rot, hip, knee, ankle = _leg(rng, 32)
    for r in fl.solve_leg(parent_rot, hip, knee, ankle, ankle[:, :3, 3].copy(), np.zeros(32)):
        assert np.abs(r - np.eye(3)).max() < 1e-12


def _walk_layers(bake, roles, n, phase):
    layers = empty_layers(n, 4)
    layers[:, 0, CLIP] = bake.clip_index(roles["walk"])
    layers[:, 0, PHASE] = phase
    layers[:, 0, WEIGHT] = 1.0
    layers[:, :, MASK] = -1
    return layers


class Course:
    """Agents walking the built-in walk, each with its own trouble: straight (0), turning at 1.5 and 4
    rad/s about its origin (1, 2), pushed sideways at 0.3 m/s (3), standing in idle and turning (4),
    teleported 5 m at frame 60 (5); sizes 0.92 to 1.08."""

    def __init__(self, bake, roles):
        self.bake, self.roles = bake, roles
        self.n = 6
        self.walk = bake.clips[bake.clip_index(roles["walk"])]
        self.speed = 0.9 / self.walk.duration
        self.x = np.zeros(self.n)
        self.z = np.zeros(self.n)
        self.yaw = np.zeros(self.n)
        self.scale = np.linspace(0.92, 1.08, self.n)
        self.phase = 0.0
        self.frame = 0

    def layers(self):
        layers = _walk_layers(self.bake, self.roles, self.n, self.phase)
        layers[4, 0, CLIP] = self.bake.clip_index(self.roles["idle"])
        return layers

    def advance(self):
        """One DT on: returns the ground step (N, 2) for the next frame's motion."""
        before = np.stack([self.x, self.z], 1)
        self.phase = (self.phase + DT / self.walk.duration) % 1.0
        self.yaw = self.yaw + np.array([0.0, 1.5, 4.0, 0.0, 2.0, 0.0]) * DT
        forward = self.speed * DT * self.scale
        forward[4] = 0.0
        self.x += forward * np.sin(self.yaw)
        self.z += forward * np.cos(self.yaw)
        self.x[3] += 0.3 * DT  # pushed sideways
        self.frame += 1
        if self.frame == 60:
            self.x[5] += 5.0
        return np.stack([self.x, self.z], 1) - before

    def motion(self, step):
        return np.column_stack([step, np.sin(self.yaw) * self.scale, np.cos(self.yaw) * self.scale]).astype(np.float32)


def _feet_world(palette, skeleton, course):
    feet = foot_joints(skeleton)
    model = joint_positions(palette, skeleton, feet)
    ground = np.stack([course.x, course.z], 1)
    return np.stack([to_world(model[i:i + 1], ground[i:i + 1], course.yaw[i], course.scale[i])[0] for i in range(course.n)])


def test_the_gpu_lock_and_its_twin_agree_frame_by_frame(gl_context, walker):
    """Each frame the twin starts from the GPU's state (a decision taken within float32 rounding of a
    threshold may go the other way, and a step then starts a frame apart; from the same state they
    must agree): the same decisions, and joint positions within 0.05 mm."""
    _compute(gl_context)
    character, bake, legs, roles = walker
    course = Course(bake, roles)
    proc = AnimationProcessor(gl_context, bake, 4, path="compute", legs=legs)
    try:
        proc.resize(course.n)
        twin = fl.FootLockTwin(legs, course.n)
        step = np.zeros((course.n, 2))
        bind = np.linalg.inv(character.skeleton.inverse_bind)[:, :, 3]
        modes, worst, seen = [], 0.0, set()
        for _ in range(240):
            layers, motion = course.layers(), course.motion(step)
            twin.state = proc.read_lock_state().astype(np.float64)
            proc.process(layers, motion, DT)
            ref = reference_palette(bake, layers, foot_lock=twin, motion=motion.astype(np.float64), dt=DT)
            gpu_state = proc.read_lock_state()
            modes.append(np.minimum(gpu_state[..., 3], fl.STEPPING) == np.minimum(twin.state[..., 3], fl.STEPPING))
            seen |= set(np.minimum(gpu_state[..., 3], fl.STEPPING).ravel().tolist())
            if modes[-1].all():
                gpu = proc.read_palette().astype(np.float64)
                worst = max(worst, float(np.abs(np.einsum("njrc,jc->njr", gpu - ref, bind)).max()))
            step = course.advance()
        assert np.mean(modes) > 0.99
        assert worst < 5e-5, f"GPU and twin joints {worst * 1e3:.4f} mm apart"
        assert {fl.FREE, fl.HELD, fl.STEPPING} <= seen  # the course went through holding, lifting and stepping
    finally:
        proc.release()


def test_a_turning_walk_stops_sliding_and_a_pushed_foot_steps(walker):
    """On the twin: the turning walkers' feet slide a tenth or less of what they did unlocked; the
    pushed agent's feet step (out of contact) rather than slide; the teleported one is not dragged back."""
    character, bake, legs, roles = walker
    course = Course(bake, roles)
    twin = fl.FootLockTwin(legs, course.n)
    step = np.zeros((course.n, 2))
    locked, free, ground, lifted = [], [], [], []
    for _ in range(300):
        layers, motion = course.layers(), course.motion(step)
        locked.append(_feet_world(reference_palette(bake, layers, foot_lock=twin, motion=motion, dt=DT), character.skeleton, course))
        free.append(_feet_world(reference_palette(bake, layers), character.skeleton, course))
        ground.append(np.stack([course.x, course.z], 1).copy())
        lifted.append(twin.state[:, :, 3] >= fl.STEPPING)
        step = course.advance()
    locked, free, ground = np.array(locked), np.array(free), np.array(ground)
    names = [character.skeleton.names[j] for j in foot_joints(character.skeleton)]
    for agent in (1, 2, 3):
        walked = float(np.linalg.norm(np.diff(ground[:, agent], axis=0), axis=1).sum())
        before = measure(free[:, agent], DT, walked, names).slide_cm_per_m
        after = measure(locked[:, agent], DT, walked, names).slide_cm_per_m
        assert after < 0.1 * before, (agent, before, after)
    assert np.array(lifted)[:, 3].any()  # the pushed agent stepped
    late = slice(90, 300)  # after the teleport at frame 60, its feet are its own again
    walked = float(np.linalg.norm(np.diff(ground[late, 5], axis=0), axis=1).sum())
    assert measure(locked[late, 5], DT, walked, names).slide_cm_per_m < 0.1


def test_legs_with_nothing_to_correct_get_the_unlocked_palette_bit_for_bit(gl_context, walker):
    _compute(gl_context)
    _, bake, legs, roles = walker
    n = 40
    layers = _walk_layers(bake, roles, n, np.linspace(0, 1, n, endpoint=False))
    yaw = np.linspace(0, 6, n)
    motion = np.column_stack([np.zeros((n, 2)), np.sin(yaw), np.cos(yaw)]).astype(np.float32)
    plain = AnimationProcessor(gl_context, bake, 4, path="compute")
    locked = AnimationProcessor(gl_context, bake, 4, path="compute", legs=legs)
    try:
        plain.resize(n)
        locked.resize(n)
        plain.process(layers)
        locked.process(layers, motion, DT)  # the first frame: every leg engages where its clip puts it
        assert np.array_equal(plain.read_palette(), locked.read_palette())
        held = locked.read_lock_state()[..., 3] == fl.HELD
        assert held.any() and not held.all()  # some feet were down, some in the air
    finally:
        plain.release()
        locked.release()


@pytest.mark.parametrize("motion, dt, message", [
    (None, DT, "needs each agent's motion"),
    (np.zeros((3, 3)), DT, r"must be \(4, 4\)"),
    (np.array([[0, 0, 0, 1]] * 3 + [[np.nan, 0, 0, 1]]), DT, "agent 3 is not finite"),
    (np.array([[0, 0, 0, 1]] * 3 + [[0, 0, 0, 0]]), DT, "agent 3 has front"),
    (np.array([[0, 0, 0, 1]] * 4), -0.1, "frame time >= 0"),
    (np.array([[0, 0, 0, 1]] * 4), float("nan"), "frame time >= 0"),
    (np.array([[0, 0, 0, 1]] * 4), float("inf"), "frame time >= 0"),
])
def test_bad_lock_input_is_one_line(gl_context, walker, motion, dt, message):
    _compute(gl_context)
    _, bake, legs, roles = walker
    proc = AnimationProcessor(gl_context, bake, 4, path="compute", legs=legs)
    try:
        proc.resize(4)
        with pytest.raises(ProcessorError, match=message) as err:
            proc.upload(_walk_layers(bake, roles, 4, 0.0), motion, dt)
        assert "\n" not in str(err.value)
    finally:
        proc.release()


def test_a_huge_frame_time_lands_every_step(gl_context, walker):
    _compute(gl_context)
    _, bake, legs, roles = walker
    proc = AnimationProcessor(gl_context, bake, 4, path="compute", legs=legs)
    try:
        proc.resize(1)
        layers = _walk_layers(bake, roles, 1, 0.0)
        proc.process(layers, np.array([[0, 0, 0, 1]], np.float32), DT)
        proc.process(layers, np.array([[0.2, 0, 0, 1]], np.float32), DT)  # pushed 20 cm: a step starts
        stepping = proc.read_lock_state()[0, :, 3] >= fl.STEPPING
        assert stepping.sum() == 1  # one foot at a time while the other stands
        for _ in range(2):
            proc.process(layers, np.array([[0, 0, 0, 1]], np.float32), 1e6)  # a step that was under way lands at once
            state = proc.read_lock_state()[0]
            assert np.all(np.isfinite(state)) and not (state[stepping, 3] >= fl.STEPPING).any()
            assert proc.nan_rows() == 0
            stepping = state[:, 3] >= fl.STEPPING  # the other foot, held too far too, steps once this one stands
        assert not stepping.any()
    finally:
        proc.release()


def test_the_fragment_path_refuses_the_lock(gl_context, walker):
    _, bake, legs, _ = walker
    with pytest.raises(ProcessorError, match="compute path"):
        AnimationProcessor(gl_context, bake, 4, path="fragment", legs=legs)


def test_the_lock_buffers_follow_the_agents_and_keep_the_kept_agents_state(gl_context, walker):
    _compute(gl_context)
    _, bake, legs, roles = walker
    proc = AnimationProcessor(gl_context, bake, 4, path="compute", legs=legs)
    try:
        for n in (0, 5, 1000, 3, 0, 7):
            proc.resize(n)
            assert proc.gpu_bytes()["foot_lock"] == n * len(legs) * 16 + n * 16
            if n:
                proc.process(_walk_layers(bake, roles, n, 0.3), np.column_stack([np.zeros((n, 3)), np.ones(n)]), DT)  # facing +z
        before = proc.read_lock_state()
        proc.resize(9)
        assert np.array_equal(proc.read_lock_state()[:7], before)
        assert not proc.read_lock_state()[7:].any()
        proc.reset_lock()
        assert not proc.read_lock_state().any()
    finally:
        proc.release()
    plain = AnimationProcessor(gl_context, bake, 4)
    try:
        plain.resize(10)
        assert plain.gpu_bytes()["foot_lock"] == 0  # off: no buffer
    finally:
        plain.release()


def test_legs_without_foot_names_are_found_by_their_shape():
    # CesiumMan's kind: "leg_joint_L_1" to "_5"; a tail that hangs low but does not rise is no leg.
    names = ["pelvis", "leg_L_1", "leg_L_2", "leg_L_3", "leg_L_5", "leg_R_1", "leg_R_2", "leg_R_3", "leg_R_5", "spine", "head", "tail_1", "tail_2", "tail_3"]
    parents = [-1, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 0, 11, 12]
    pos = [(0, 0.9, 0), (0.1, 0.88, 0), (0.1, 0.48, 0.01), (0.1, 0.08, -0.01), (0.1, 0.02, 0.12), (-0.1, 0.88, 0), (-0.1, 0.48, 0.01),
           (-0.1, 0.08, -0.01), (-0.1, 0.02, 0.12), (0, 1.3, 0), (0, 1.7, 0), (0, 0.85, -0.2), (0, 0.6, -0.4), (0, 0.1, -0.5)]
    legs = fl.find_legs(_skeleton(names, parents, pos))
    assert set(legs.names) == {"leg_L_3", "leg_R_3"}
    assert {names[t] for t in legs.toe} == {"leg_L_5", "leg_R_5"}


def test_cesium_man_s_legs_are_found():
    from conftest import shared

    from crowd.asset.gltf import load_character

    character = load_character(shared("CesiumMan.glb"))
    legs = fl.find_legs(character.skeleton)
    assert set(legs.names) == {"leg_joint_L_3", "leg_joint_R_3"}
    assert np.all(legs.lowest[:, 0] > 0.05) and np.all(legs.lowest[:, 0] < 0.12)  # Z-up in the file, Y-up as composed


def test_the_pipeline_reports_and_switches_the_lock(gl_context):
    from crowd.gl import Offscreen
    from crowd.pipeline import CrowdPipeline
    from crowd.pipeline_config import PipelineConfig

    with Offscreen(gl_context, (96, 54)) as target, CrowdPipeline(gl_context, PipelineConfig(agents=20)) as p:
        p.frame(target.framebuffer, 1 / 30)
        if gl_context.version_code >= 430:
            assert p.foot_lock_state() == {"on": True, "legs": ["foot_l", "foot_r"]}
            assert p.gpu_bytes()["foot_lock"] == 20 * 2 * 16 + 20 * 16
        p.set("foot_lock", False)
        p.frame(target.framebuffer, 1 / 30)
        assert p.foot_lock_state()["why"] == "off in the scene" and p.gpu_bytes()["foot_lock"] == 0
        p.set("foot_lock", True)
        p.set("processor", "fragment")
        p.frame(target.framebuffer, 1 / 30)
        state = p.foot_lock_state()
        assert not state["on"] and "fragment path" in state["why"] and p.gpu_bytes()["foot_lock"] == 0
        assert p.processor.nan_rows() == 0
