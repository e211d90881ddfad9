import numpy as np
import pytest

from crowd.anim import reference
from crowd import transforms as tf
from crowd.asset.model import ModelError


def test_negative_weights_count_as_zero_and_zero_total_falls_back_to_rest(zombie):
    sk = zombie.skeleton
    walk = reference.sample_clip(sk, zombie.clip("shamble"), [0.3])
    run = reference.sample_clip(sk, zombie.clip("run"), [0.3])
    only_walk = reference.blend(sk, [walk, run], [[1.0], [-5.0]])
    np.testing.assert_allclose(only_walk.rotation, walk.rotation, atol=1e-12)
    rest = reference.blend(sk, [walk, run], [[0.0], [-1.0]])
    np.testing.assert_allclose(rest.rotation[0], sk.rest_rotation, atol=1e-12)
    np.testing.assert_allclose(rest.translation[0], sk.rest_translation, atol=1e-12)


def test_weights_need_not_sum_to_one(zombie):
    sk = zombie.skeleton
    a = reference.sample_clip(sk, zombie.clip("shamble"), [0.1])
    b = reference.sample_clip(sk, zombie.clip("idle"), [0.7])
    x = reference.blend(sk, [a, b], [[0.2], [0.6]])
    y = reference.blend(sk, [a, b], [[1.0], [3.0]])
    np.testing.assert_allclose(x.rotation, y.rotation, atol=1e-12)
    np.testing.assert_allclose(x.translation, y.translation, atol=1e-12)


def test_antipodal_layers_are_aligned_before_summing(zombie):
    sk = zombie.skeleton
    a = reference.rest_pose(sk)
    b = reference.rest_pose(sk)
    q = tf.quat_from_axis_angle([0.0, 0.0, 1.0], 0.5)
    a.rotation[0, 1] = q
    b.rotation[0, 1] = -q  # the same rotation with the other sign
    out = reference.blend(sk, [a, b], [[0.5], [0.5]])
    assert abs(np.dot(out.rotation[0, 1], q)) == pytest.approx(1.0, abs=1e-12)


def test_joint_mask_limits_a_layer(zombie):
    sk = zombie.skeleton
    walk = reference.sample_clip(sk, zombie.clip("shamble"), [0.2])
    attack = reference.sample_clip(sk, zombie.clip("attack"), [0.4])
    upper = np.zeros((2, sk.joint_count))
    upper[0] = 1.0
    upper[1, [sk.index(n) for n in ("chest", "shoulder_r", "upper_arm_r", "forearm_r", "hand_r")]] = 1.0
    out = reference.blend(sk, [walk, attack], [[1.0], [100.0]], masks=upper)
    thigh = sk.index("thigh_l")
    np.testing.assert_allclose(out.rotation[0, thigh], walk.rotation[0, thigh], atol=1e-12)
    arm = sk.index("upper_arm_r")
    assert abs(np.dot(out.rotation[0, arm], attack.rotation[0, arm])) > 0.9999


def test_loop_phase_wraps_in_float64_and_one_shots_clamp(zombie):
    shamble, death = zombie.clip("shamble"), zombie.clip("death")
    assert reference.phase_to_time(shamble, 36000.25) == pytest.approx(0.25 * shamble.duration, abs=1e-9)
    assert reference.phase_to_time(death, 7.0) == pytest.approx(death.end)
    with pytest.raises(ModelError, match="NaN"):
        reference.phase_to_time(shamble, float("nan"))


def test_linear_rotation_is_a_slerp():
    a = tf.quat_from_axis_angle([0.0, 1.0, 0.0], 0.0)
    b = tf.quat_from_axis_angle([0.0, 1.0, 0.0], 2.0)
    mid = tf.quat_slerp(a, b, 0.25)
    np.testing.assert_allclose(mid, tf.quat_from_axis_angle([0.0, 1.0, 0.0], 0.5), atol=1e-12)


def test_nan_weights_are_refused(zombie):
    sk = zombie.skeleton
    p = reference.rest_pose(sk)
    with pytest.raises(ModelError, match="NaN"):
        reference.blend(sk, [p], [[float("nan")]])
