import numpy as np
import pytest

from conftest import shared, shared_files
from crowd.anim import reference
from crowd import transforms as tf
from crowd.anim.bake import BakeError, bake, joint_position_error, storage_error
from crowd.asset.gltf import load_character
from crowd.asset.model import Channel, Clip, Skeleton

KEY_BOUND_M = {"f32": 2e-6, "f16": 3e-3}  # at the bake keys: storage rounding only


def key_phases(b, ci):
    n = b.clips[ci].frame_count
    return np.arange(n) / (n - 1)


@pytest.mark.parametrize("precision", ["f32", "f16"])
def test_zombie_bake_matches_reference_at_keys(zombie, precision):
    b = bake(zombie.skeleton, zombie.clips, 15, precision)
    assert b.texels.dtype == {"f32": np.float32, "f16": np.float16}[precision]
    for clip in zombie.clips:
        ci = b.clip_index(clip.name)
        err = joint_position_error(b, zombie.skeleton, clip, key_phases(b, ci))
        assert err.max() < KEY_BOUND_M[precision], clip.name


def test_zombie_bake_between_keys_is_bounded_and_shrinks_with_rate(zombie):
    """Between keys the error is the lerp's; measured, it must fall as the bake rate rises."""
    phases = np.linspace(0.0, 1.0, 301)
    worst = {}
    for fps in (15, 30, 60):
        b = bake(zombie.skeleton, zombie.clips, fps)
        worst[fps] = max(joint_position_error(b, zombie.skeleton, c, phases).max() for c in zombie.clips)
    assert worst[60] < worst[30] < worst[15] < 0.15  # metres; see docs/BENCHMARKS.md for per-clip figures
    assert worst[30] < 1e-3  # the 30 fps bake's keys are the source's own 30 fps keys


def test_frames_land_on_source_keys_despite_float32_durations(zombie):
    """glTF key times are float32: the 1.2 s attack lasts 1.2000000477 s. A 60 fps bake must still
    take 72 intervals (not 73), so every other frame is a source key and the drift error is gone."""
    attack = zombie.clip("attack")
    assert attack.duration != 1.2 and attack.duration == pytest.approx(1.2, abs=1e-6)
    b = bake(zombie.skeleton, [attack], 60)
    assert b.clips[0].frame_count == 73
    phases = np.arange(37) / 36.0  # the source's 30 fps keys
    assert joint_position_error(b, zombie.skeleton, attack, phases).max() < 1e-5


def test_source_rate_puts_frames_on_the_clips_own_keys(zombie):
    source = bake(zombie.skeleton, zombie.clips, "source")
    at_30 = bake(zombie.skeleton, zombie.clips, 30)
    assert source.fps == "source"
    assert [c.frame_count for c in source.clips] == [c.frame_count for c in at_30.clips]
    np.testing.assert_array_equal(source.texels, at_30.texels)


def test_frame_zero_is_inverse_bind_and_rest_pose_gives_identity(zombie):
    b = bake(zombie.skeleton, zombie.clips, 15)
    np.testing.assert_allclose(b.inverse_bind(), zombie.skeleton.inverse_bind, atol=1e-6)
    bind = reference.global_matrices(zombie.skeleton, reference.rest_pose(zombie.skeleton))[0]
    np.testing.assert_allclose(bind @ b.inverse_bind(), np.tile(np.eye(4), (zombie.skeleton.joint_count, 1, 1)), atol=1e-6)


def test_layout_and_clip_table(zombie):
    b = bake(zombie.skeleton, zombie.clips, 15)
    assert b.texels.shape[1:] == (2 * zombie.skeleton.joint_count, 4)
    table = b.clip_table
    assert table[0, 0] == 1  # clips start after the inverse-bind row
    for (first, count, fps, loop), info, clip in zip(table, b.clips, zombie.clips):
        assert count == info.frame_count and bool(loop) == clip.loop
        assert fps == pytest.approx((count - 1) / clip.duration, rel=1e-6) and fps >= 15 * (1 - 1e-5)
    assert table[-1, 0] + table[-1, 1] == b.rest_row == b.rows - 1
    assert np.all(b.parents == zombie.skeleton.parents)
    rest = np.concatenate([zombie.skeleton.rest_rotation, tf.dq_from_rt(zombie.skeleton.rest_rotation, zombie.skeleton.rest_translation)[1]], axis=1)
    assert np.allclose(b.texels[b.rest_row].astype(np.float64).reshape(-1, 2, 4).reshape(-1, 8), rest, atol=1e-6)
    assert b.scale is None  # the zombie has no joint scale: no scale texture


def test_keys_are_sign_aligned_including_the_loop_wrap(zombie):
    b = bake(zombie.skeleton, zombie.clips, 15)
    real = b.texels[:, 0::2].astype(np.float64)
    for info in b.clips:
        rows = real[info.first_row : info.first_row + info.frame_count]
        assert np.all(np.sum(rows[1:] * rows[:-1], axis=-1) >= 0.0), info.name


def spinning_skeleton_and_clip():
    """One joint turning a full 360° over a looping clip: its quaternion ends at -q (antipodal keys)."""
    sk = Skeleton(("root", "arm"), np.array([-1, 0], dtype=np.int32), np.array([[0, 0, 0], [1.0, 0, 0]]),
                  tf.quat_identity((2,)), np.ones((2, 3)), np.tile(np.eye(4), (2, 1, 1)))
    sk.inverse_bind = np.linalg.inv(reference.global_matrices(sk, reference.rest_pose(sk))[0])
    times = np.linspace(0.0, 1.0, 9)
    q = tf.quat_from_axis_angle([0.0, 1.0, 0.0], times * 2 * np.pi)
    q[-1] = q[0]  # the file stores the closing key as +q, the slerp takes the short way from key 7
    return sk, Clip("spin", [Channel(0, "rotation", "LINEAR", times, q)], 0.0, 1.0, True)


def test_antipodal_keys_and_loop_wrap():
    sk, clip = spinning_skeleton_and_clip()
    b = bake(sk, [clip], 16)
    real = b.texels[1 : b.rest_row, 0].astype(np.float64)  # the clip's rows, without the rest row
    assert np.all(np.sum(real[1:] * real[:-1], axis=-1) > 0)
    assert np.dot(real[-1], real[0]) < 0  # the closing key is -q of the first: a wrap the texture never lerps
    phases = np.concatenate([np.linspace(0, 1, 97, endpoint=False), [1 - 1e-9, 1.0, 1.5, 10 * 3600.0 + 0.25]])
    err = joint_position_error(b, sk, clip, phases)
    assert err.max() < 0.02  # the lerp's chord error at 16 keys per turn on a 1 m arm


def test_f16_halves_the_bytes(zombie):
    a, h = bake(zombie.skeleton, zombie.clips, 15, "f32"), bake(zombie.skeleton, zombie.clips, 15, "f16")
    assert h.texels.nbytes * 2 == a.texels.nbytes


def test_only_requested_clips_are_baked(zombie):
    b = bake(zombie.skeleton, [zombie.clip("shamble"), zombie.clip("idle")], 15)
    assert [c.name for c in b.clips] == ["shamble", "idle"]
    with pytest.raises(BakeError, match="was not baked"):
        b.clip_index("run")


@pytest.mark.parametrize("fps, precision, message", [(0, "f32", "bake rate"), (float("nan"), "f32", "bake rate"),
                                                     (1e9, "f32", "bake rate"), (15, "f8", "precision")])
def test_bad_bake_arguments(zombie, fps, precision, message):
    with pytest.raises(BakeError, match=message):
        bake(zombie.skeleton, zombie.clips, fps, precision)


def test_too_many_frames_for_a_texture(zombie):
    with pytest.raises(BakeError, match="do not fit"):
        bake(zombie.skeleton, zombie.clips, 240, max_rows=1024)


def test_hedgehog_animated_scale_gets_a_scale_channel():
    c = load_character(shared("Quaternius_CubeWorld_Hedgehog.gltf"))
    b = bake(c.skeleton, c.clips, 30)
    assert b.scale is not None and b.scale.max() > 1.1
    for clip in c.clips:
        ci = b.clip_index(clip.name)
        assert joint_position_error(b, c.skeleton, clip, key_phases(b, ci)).max() < 1e-5


@pytest.mark.parametrize("path", shared_files(), ids=lambda p: p.name)
def test_shared_files_bake_matches_reference_at_keys(path):
    c = load_character(path)
    b = bake(c.skeleton, c.clips, 15)
    for clip in c.clips:
        ci = b.clip_index(clip.name)
        assert joint_position_error(b, c.skeleton, clip, key_phases(b, ci)).max() < 5e-5, clip.name


def growing_joint(scale_max: float, child_m: float):
    """A root whose scale grows from 1 to `scale_max` over a one-shot clip, with a child `child_m` out."""
    sk = Skeleton(("root", "tip"), np.array([-1, 0], dtype=np.int32), np.array([[0, 0, 0], [child_m, 0, 0]]),
                  tf.quat_identity((2,)), np.ones((2, 3)), np.tile(np.eye(4), (2, 1, 1)))
    sk.inverse_bind = np.linalg.inv(reference.global_matrices(sk, reference.rest_pose(sk))[0])
    times = np.linspace(0.0, 1.0, 31)
    s = np.repeat((1.0 + (scale_max - 1.0) * times)[:, None], 3, axis=1)
    return sk, Clip("grow", [Channel(0, "scale", "LINEAR", times, s)], 0.0, 1.0, False)


def test_f16_storage_error_is_measured_and_warned_about():
    """A joint scaled 1e4 times with a child 0.3 m out: f16 steps 8 near 1e4, so the child lands 0.84 m
    off, which the bake used to accept silently. It measures the stored keys against the float64 ones
    at every bake frame and warns (naming joint, clip and frame, and what f32 gives); the measure is
    the error against the source reference at the keys."""
    sk, clip = growing_joint(1e4, 0.3)
    b16 = bake(sk, [clip], 30, "f16")
    key_error = joint_position_error(b16, sk, clip, key_phases(b16, 0)).max()
    assert key_error > 0.5
    assert len(b16.warnings) == 1
    line = b16.warnings[0]
    assert "\n" not in line and "f16 storage" in line and "'tip'" in line and "clip 'grow', frame" in line and "f32" in line
    b32 = bake(sk, [clip], 30, "f32")
    assert b32.warnings == [] and joint_position_error(b32, sk, clip, key_phases(b32, 0)).max() < 1e-3
    # The f32 keys stand in for the float64 ones the bake measured against (they are 1e4 times closer).
    measured, row, joint = storage_error(b32.texels.astype(np.float64), b32.scale.astype(np.float64), b16.texels, b16.scale, sk.parents)
    assert joint == 1 and b16.clips[0].first_row <= row < b16.rest_row
    assert f"{measured * 1e3:.3g} mm" in line


def test_storage_error_matches_the_reference_at_the_keys():
    sk, clip = growing_joint(1e4, 0.3)
    b = bake(sk, [clip], 30, "f16")
    stated = float(b.warnings[0].split("moves joint 'tip' ")[1].split(" mm")[0]) * 1e-3
    assert stated == pytest.approx(joint_position_error(b, sk, clip, key_phases(b, 0)).max(), rel=1e-2)


def test_the_zombie_in_f16_is_warned_about_and_in_f32_is_not(zombie):
    """f16's floor on the zombie is just above the 1 mm target (1.03 mm at hand_r_socket): a warning, and
    the bake goes on (refusing would take f16 from the character it is for)."""
    b16 = bake(zombie.skeleton, zombie.clips, 30, "f16")
    assert len(b16.warnings) == 1 and "f16 storage moves joint 'hand_r_socket' 1.03 mm" in b16.warnings[0]
    assert bake(zombie.skeleton, zombie.clips, 30, "f32").warnings == []


def test_a_bake_too_long_for_the_texture_is_refused_before_sampling(zombie, monkeypatch):
    """An hour-long clip at 30 fps needs 108,003 rows: refused from the count, before any pose is sampled."""
    import dataclasses

    from crowd.anim import bake as bake_module
    from crowd.anim.bake import BakeError

    def no_sampling(*args, **kwargs):
        raise AssertionError("the bake sampled poses before checking that its rows fit")

    monkeypatch.setattr(bake_module.reference, "sample_clip", no_sampling)
    clip = zombie.clips[0]
    hour = dataclasses.replace(clip, end=clip.start + 3600.0)
    with pytest.raises(BakeError, match="108003 frames do not fit a 16384-row texture"):
        bake(zombie.skeleton, [hour], 30)
