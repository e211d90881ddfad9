"""Issue 18, point 5 (numerics): each claim checked against the float64 reference (crowd.anim.reference).

- the panel's forced "play" wraps its phase in float64 before it reaches the float32 layers;
- the processor refuses phases float32 cannot hold to within 1e-6 cycles, rather than rounding them;
- quaternion signs are aligned to the anchor (the first layer with a weight above 0), so that a small
  change of weight moves a point by at most a bound proportional to it, on the reference, its float64
  model of the processor and both GPU paths;
- the rest-pose threshold is relative to the summed layer weights;
- degenerate sums (q and -q exactly on the edge of the anchor's hemisphere, weights of 1e-30) neither
  cancel nor give NaN.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from crowd import transforms as tf
from crowd.anim import reference
from crowd.anim.bake import bake
from crowd.anim.processor import AnimationProcessor
from crowd.anim.palette_reference import palette_joint_positions, reference_palette
from crowd.asset.model import Channel, Clip, Skeleton
from crowd.frame import CLIP, MASK, PHASE, WEIGHT, FrameError, ForcedClip, LayerOverrides, empty_layers, validate_layers

PATHS = ("compute", "fragment")
ARM_M = 0.9  # the arm's reach: the tip joint sits 0.9 m from the turning root


def joint_positions(skeleton, clip, phases) -> np.ndarray:
    return reference.global_matrices(skeleton, reference.sample_clip(skeleton, clip, phases))[..., :3, 3]


def exact_phase(time: float, start: float, speed: float, duration: float) -> float:
    return float(((Fraction(time) - Fraction(start)) * Fraction(speed) / Fraction(duration)) % 1)


# -- 1. the forced clip's phase


@pytest.mark.parametrize("hours", [10, 1000])
def test_forced_play_wraps_its_phase_in_float64(zombie, hours):
    """After 10 and 1000 hours of forced play the layer's phase is within float32's rounding of [0, 1)
    (3e-8 cycles) of the exact phase, so the pose is within a micrometre of the float64 reference's. The
    unwrapped float32 phase this used to write is measured alongside: 4.4 mm after 10 hours, 457 mm
    after 1000 on the run clip."""
    run = zombie.clip("run")
    sk = zombie.skeleton
    worst, unwrapped = 0.0, 0.0
    for start in (0.0, 17.3, 1234.5678):
        for speed in (0.8, 1.0, 1.3):
            time = start + hours * 3600.0 + 0.123
            layers = empty_layers(3)
            LayerOverrides(ForcedClip(2, start)).apply(layers, time, run.duration, speed, True)
            phase = layers[:, 0, PHASE]
            assert np.all(layers[:, 0, CLIP] == 2) and np.all(layers[:, 0, WEIGHT] == 1.0)
            assert np.all((phase >= 0.0) & (phase < 1.0))
            exact = exact_phase(time, start, speed, run.duration)
            truth = joint_positions(sk, run, [exact])
            worst = max(worst, float(np.max(np.linalg.norm(joint_positions(sk, run, phase[:1].astype(np.float64)) - truth, axis=-1))))
            raw = np.float32((time - start) * speed / run.duration)
            unwrapped = max(unwrapped, float(np.max(np.linalg.norm(joint_positions(sk, run, [float(raw)]) - truth, axis=-1))))
    assert worst < 1e-6, f"{worst * 1e3:.4f} mm"
    assert unwrapped > {10: 1e-3, 1000: 0.1}[hours]  # the test sees what the old code did
    validate_layers(layers, 7, 0, 4)  # and the processor's door accepts the wrapped phase


def test_forced_one_shot_clamps_and_the_wrap_never_reaches_one():
    o = LayerOverrides(ForcedClip(0, 100.0))
    assert o.forced_phase(100.0 + 3600.0, 2.2, 1.0, False) == 1.0
    assert o.forced_phase(99.0, 2.2, 1.0, False) == 0.0
    assert o.forced_phase(100.0 + 1.1, 2.2, 1.0, False) == pytest.approx(0.5)
    wrapped = o.forced_phase(100.0 - 1e-12, 2.2, 1.0, True)  # a hair before the start: just under 1, or 0
    assert 0.0 <= wrapped < 1.0


# -- 2. phases float32 cannot hold


def test_the_phase_limit_is_where_float32_stops_holding_1e_6_cycles():
    below = np.float32(32.0) - np.spacing(np.float32(31.0))
    assert np.spacing(below) / 2 <= 1e-6 < np.spacing(np.float32(32.0)) / 2


@pytest.mark.parametrize("phase", [32.0, -32.0, 1e5, 1e7, 3.4e38])
def test_phases_float32_cannot_hold_are_refused_in_one_line(phase):
    layers = empty_layers(5, 3)
    layers[:, :, WEIGHT] = 1.0
    layers[3, 2, PHASE] = phase
    with pytest.raises(FrameError, match=r"agent 3, layer 2") as caught:
        validate_layers(layers, 2, 0, 3)
    assert "\n" not in str(caught.value) and "float32" in str(caught.value)


def test_float64_phases_are_refused_before_they_are_rounded():
    """1e5 + 0.3 cycles in float64: the float32 layer would hold 1e5 + 0.3125, 0.0125 cycles off."""
    layers = np.zeros((2, 1, 4))
    layers[:, 0, MASK] = -1.0
    layers[:, 0, WEIGHT] = 1.0
    layers[1, 0, PHASE] = 1e5 + 0.3
    with pytest.raises(FrameError, match=r"agent 1, layer 0"):
        validate_layers(layers, 1, 0, 1)


def test_phases_float32_holds_pass_and_round_within_1e_6_cycles():
    phases = np.array([-31.999998, -1.5, 0.0, 0.999999, 2.0, 17.25, 31.999998])
    layers = np.zeros((len(phases), 1, 4))
    layers[:, 0, MASK] = -1.0
    layers[:, 0, PHASE] = phases
    out = validate_layers(layers, 1, 0, 1)
    assert np.max(np.abs(out[:, 0, PHASE].astype(np.float64) - phases)) <= 1e-6


def test_the_processor_and_its_model_refuse_them_too(gl_context, zombie):
    baked = bake(zombie.skeleton, zombie.clips, 15)
    layers = empty_layers(4, 1)
    layers[:, 0, WEIGHT] = 1.0
    layers[2, 0, PHASE] = 1e5
    with pytest.raises(FrameError, match="agent 2, layer 0"):
        reference_palette(baked, layers)
    proc = AnimationProcessor(gl_context, baked, 1)
    try:
        proc.resize(4)
        with pytest.raises(FrameError, match="agent 2, layer 0"):
            proc.upload(layers)
    finally:
        proc.release()


# -- 3. sign alignment: a small change of weight, a small move


def arm() -> Skeleton:
    """4 joints along +X, 0.3 m apart: the root turns, the tip is 0.9 m out."""
    parents = np.arange(-1, 3, dtype=np.int32)
    rest_t = np.tile([0.3, 0.0, 0.0], (4, 1))
    rest_t[0] = 0.0
    glob = np.tile(np.eye(4), (4, 1, 1))
    glob[:, 0, 3] = np.arange(4) * 0.3
    return Skeleton(tuple(f"arm{j}" for j in range(4)), parents, rest_t, tf.quat_identity((4,)), np.ones((4, 3)), np.linalg.inv(glob))


def tips(skeleton, rotations, weights, masks=None) -> np.ndarray:
    """Tip positions (P, 3) of the reference blend of root rotations (L, P, 4) at weights (L, P)."""
    poses = []
    for q in rotations:
        pose = reference.rest_pose(skeleton, q.shape[0])
        pose.rotation[:, 0] = q
        poses.append(pose)
    return reference.global_matrices(skeleton, reference.blend(skeleton, poses, weights, masks))[:, -1, :3, 3]


def heaviest_aligned_tips(rotations, weights) -> np.ndarray:
    """The rule this replaced (signs aligned to the heaviest layer), to show the search below finds its
    jumps: the test would catch a return to it."""
    w = np.maximum(weights, 0.0)
    ref = np.take_along_axis(rotations, np.argmax(w, axis=0)[None, :, None], axis=0)[0]
    sign = np.where(np.sum(rotations * ref[None], axis=-1) < 0.0, -1.0, 1.0)
    q = tf.quat_normalize(np.sum((w * sign)[..., None] * rotations, axis=0))
    return tf.quat_rotate(q, np.array([ARM_M, 0.0, 0.0]))


def three_way():
    """The issue's case: 0°, +120° and -120° about one axis."""
    z = np.array([0.0, 0.0, 1.0])
    return np.stack([tf.quat_from_axis_angle(z, np.radians(a))[None] for a in (0.0, 120.0, -120.0)])


def test_a_small_weight_change_no_longer_turns_the_three_way_blend():
    """(1, 1, 1) against (1, 1 + 1e-4, 1): the tip moved 1.56 m while the heaviest layer set the signs,
    and moves 0.078 mm now, within the bound 2 R dw / w_anchor = 0.18 mm."""
    sk = arm()
    q = three_way()
    dw = 1e-4
    base = np.ones((3, 1))
    old_move = []
    for k in range(3):
        moved = base.copy()
        moved[k] += dw
        move = float(np.linalg.norm(tips(sk, q, moved) - tips(sk, q, base)))
        assert move <= 2 * ARM_M * dw, (k, move)
        old_move.append(float(np.linalg.norm(heaviest_aligned_tips(q, moved) - heaviest_aligned_tips(q, base))))
    assert max(old_move) == pytest.approx(2 * ARM_M * np.sin(np.radians(60.0)), rel=1e-3)  # 1.56 m


def random_layers_of_rotations(rng, count, layers=4, coaxial=0.5):
    """Root rotations (L, P, 4) at any angle up to 180° (either sign), about one shared axis for a
    share of the samples (the sharpest case: every pair on one great circle) or random axes; weights
    (L, P) from 0.05 to 1, some later layers exactly 0 (they may switch on)."""
    axes = rng.normal(size=(layers, count, 3))
    shared = rng.random(count) < coaxial
    axes[:, shared] = axes[0, shared][None]
    q = tf.quat_from_axis_angle(axes, rng.uniform(-np.pi, np.pi, (layers, count)))
    q *= np.where(rng.random((layers, count, 1)) < 0.5, -1.0, 1.0)
    w = rng.uniform(0.05, 1.0, (layers, count))
    w[1:][rng.random((layers - 1, count)) < 0.25] = 0.0
    return q, w


def perturb(rng, w, dw, factor=None, ties=0.3):
    """One layer's weight changed by ±dw per sample (w[0] is never 0), but never a zero weight that
    would become the anchor (its masked weight the first above 0 at the root: the one place a sign may
    change, where the anchor switches on or off); zero weights only rise. In a share `ties` of the
    samples the layer first ties the heaviest and then rises above it: where the old rule changed its
    reference. `w` is changed in place for those."""
    count = w.shape[1]
    cols = np.arange(count)
    effective = w * (np.ones(w.shape[0]) if factor is None else factor)[:, None]
    has = effective.sum(axis=0) > 0
    k = rng.integers(0, w.shape[0], count)
    allowed = (w[k, cols] > 0) | (has & (k > np.argmax(effective > 0, axis=0)))
    k = np.where(allowed, k, 0)
    step = np.where(w[k, cols] > 0, np.where(rng.random(count) < 0.5, -dw, dw), dw)
    tie = rng.random(count) < ties
    w[k[tie], cols[tie]] = w[:, tie].max(axis=0)
    step[tie] = dw
    moved = w.copy()
    moved[k, cols] += step
    return moved, k


def test_no_weight_change_moves_a_point_more_than_its_bound_on_the_reference():
    """20,000 random 2- to 4-layer blends at all angles (a half of them on one axis, where three layers
    are easily spread round the circle), with and without joint masks: a change dw of one weight moves
    the tip by at most 2 R dw m_k / (w_anchor m_anchor), the first-order bound of nlerp with an aligned
    sum of at least the anchor's weight. The same search finds metre jumps under the old rule."""
    sk = arm()
    rng = np.random.default_rng(18)
    dw = 1e-6
    worst_ratio, old_worst = 0.0, 0.0
    for masked in (False, True):
        for _ in range(5):
            q, w = random_layers_of_rotations(rng, 2000)
            masks = None
            factor = np.ones(4)
            if masked:
                factor = rng.uniform(0.0, 1.0, 4)
                factor[rng.integers(0, 4)] = 0.0  # one layer masked out at the root entirely
                masks = np.ones((4, sk.joint_count))
                masks[:, 0] = factor
            moved, k = perturb(rng, w, dw, factor)
            move = np.linalg.norm(tips(sk, q, moved, masks) - tips(sk, q, w, masks), axis=-1)
            effective = w * factor[:, None]
            has = effective.sum(axis=0) > 0
            anchor = np.argmax(effective > 0, axis=0)
            w_anchor = effective[anchor, np.arange(w.shape[1])]
            bound = 2 * ARM_M * dw * factor[k] / np.where(has, w_anchor, 1.0)
            ok = has & (factor[k] > 0)  # a layer masked out here (before the anchor or not) changes nothing
            assert np.all(move[~has] == 0.0)
            assert np.all(move[ok] <= bound[ok] * (1 + 1e-3) + 1e-12), float(np.max(move[ok] / bound[ok]))
            assert np.all(move[has & (factor[k] == 0)] <= 1e-12)
            worst_ratio = max(worst_ratio, float(np.max(move[ok] / bound[ok])))
            if not masked:
                old_worst = max(old_worst, float(np.max(np.linalg.norm(heaviest_aligned_tips(q, moved) - heaviest_aligned_tips(q, w), axis=-1))))
    assert worst_ratio > 0.3  # the bound is tight enough to mean something
    assert old_worst > 0.5  # metres: the heaviest-layer rule jumps in this search


def held(name, q, duration=0.1):
    return Clip(name, [Channel(0, "rotation", "LINEAR", np.array([0.0, duration]), np.stack([q, q]))], 0.0, duration, False)


@pytest.mark.parametrize("path", PATHS)
def test_no_weight_change_moves_a_point_more_than_its_bound_on_the_gpu(gl_context, path):
    """The same on both GPU paths and on their float64 model, 150 random 3- and 4-layer blends, and the
    three-way blend of the issue: each blend against its twin with one weight changed by 1e-3, the
    bound widened by twice the float32 tolerance of the processor tests (0.01 mm)."""
    sk = arm()
    rng = np.random.default_rng(5)
    count, lcount, dw = 150, 4, 1e-3
    q, w = random_layers_of_rotations(rng, count, lcount)
    q[:3, 0], w[:, 0] = three_way()[:, 0], [1.0, 1.0, 1.0, 0.0]  # sample 0: the case
    moved, k = perturb(rng, w, dw)
    moved[:, 0], k[0] = [1.0, 1.0 + dw, 1.0, 0.0], 1
    clips = [held(f"c{p}_{l}", q[l, p]) for p in range(count) for l in range(lcount)]
    baked = bake(sk, clips, 30)
    layers = empty_layers(2 * count, lcount)
    layers[:, :, CLIP] = np.tile(np.arange(count * lcount).reshape(count, lcount), (2, 1))
    layers[:, :, PHASE] = 0.5
    layers[:, :, WEIGHT] = np.concatenate([w.T, moved.T])
    proc = AnimationProcessor(gl_context, baked, lcount, path=path)
    try:
        proc.resize(2 * count)
        proc.process(layers)
        gpu = proc.read_palette().astype(np.float64)
    finally:
        proc.release()
    model = reference_palette(baked, layers)
    inverse_bind = sk.inverse_bind
    for palette, slack in ((gpu, 2e-5), (model, 1e-9)):
        tip = palette_joint_positions(palette, inverse_bind)[:, -1]
        move = np.linalg.norm(tip[count:] - tip[:count], axis=-1)
        anchor = np.argmax(w > 0, axis=0)
        bound = 2 * ARM_M * dw / w[anchor, np.arange(count)]
        assert np.all(move <= bound * 1.05 + slack), float(np.max(move - bound))
    old_move = np.linalg.norm(heaviest_aligned_tips(q, moved) - heaviest_aligned_tips(q, w), axis=-1)
    assert np.max(old_move - bound) > 0.5  # these samples include jumps of the old rule
    assert np.max(np.abs(gpu - model)) < 1e-5
    # Against the float64 reference: a held clip is its rotation, so the truth is the blend of those.
    ref_tips = np.concatenate([tips(sk, q, w), tips(sk, q, moved)])
    assert np.max(np.linalg.norm(palette_joint_positions(gpu, inverse_bind)[:, -1] - ref_tips, axis=-1)) < 1e-5


# -- 4. the rest threshold is relative


def test_rest_threshold_is_relative_to_the_summed_weights(zombie):
    sk = zombie.skeleton
    a = reference.sample_clip(sk, zombie.clip("shamble"), [0.1])
    b = reference.sample_clip(sk, zombie.clip("idle"), [0.7])
    tiny = reference.blend(sk, [a, b], [[2e-7], [3e-7]])
    big = reference.blend(sk, [a, b], [[2.0], [3.0]])
    np.testing.assert_allclose(tiny.rotation, big.rotation, atol=1e-12)
    np.testing.assert_allclose(tiny.translation, big.translation, atol=1e-12)
    assert np.max(np.abs(tiny.rotation[0] - sk.rest_rotation)) > 0.01  # a blend, not the rest pose
    for scale in (1e-30, 1e-12, 1e6):
        np.testing.assert_allclose(reference.blend(sk, [a, b], [[2.0 * scale], [3.0 * scale]]).rotation, big.rotation, atol=1e-12)


def test_negative_weights_do_not_count_in_the_threshold_either(zombie):
    sk = zombie.skeleton
    a = reference.sample_clip(sk, zombie.clip("shamble"), [0.1])
    b = reference.sample_clip(sk, zombie.clip("idle"), [0.7])
    np.testing.assert_allclose(reference.blend(sk, [a, b], [[1e-7], [-5.0]]).rotation, a.rotation, atol=1e-12)


def test_the_masked_share_decides_per_joint(zombie):
    """An upper-body layer of weight 1 over a whole-body layer of weight 1e-7: the legs' masked weight is
    1e-7 / (1 + 1e-7) of the sum, below 1e-6, so they rest; at 1e-5 the legs follow the whole-body layer."""
    sk = zombie.skeleton
    walk = reference.sample_clip(sk, zombie.clip("shamble"), [0.2])
    attack = reference.sample_clip(sk, zombie.clip("attack"), [0.4])
    upper = np.zeros((2, sk.joint_count))
    upper[0] = 1.0
    upper[1, [sk.index(n) for n in ("spine", "chest", "upper_arm_r", "forearm_r", "hand_r")]] = 1.0
    thigh = sk.index("thigh_l")
    at_rest = reference.blend(sk, [walk, attack], [[1e-7], [1.0]], masks=upper)
    np.testing.assert_allclose(at_rest.rotation[0, thigh], sk.rest_rotation[thigh], atol=1e-12)
    moving = reference.blend(sk, [walk, attack], [[1e-5], [1.0]], masks=upper)
    np.testing.assert_allclose(moving.rotation[0, thigh], walk.rotation[0, thigh], atol=1e-12)


# -- degenerate sums


@pytest.mark.parametrize("path", PATHS)
def test_opposite_signs_on_the_edge_of_the_anchors_hemisphere_add_up(gl_context, path):
    """An identity anchor at weight 1e-30 and the same half turn about X stored as (1, 0, 0, 0) and as
    (-1, 0, 0, 0): both dot products with the anchor are exactly 0. They must add up to the half turn,
    not cancel to the anchor, on the reference, the model and both GPU paths, finite throughout."""
    sk = arm()
    half = np.array([1.0, 0.0, 0.0, 0.0])
    rotations = np.stack([tf.quat_identity((1,)), half[None], -half[None]])
    weights = np.array([[1e-30], [1.0], [1.0]])
    tip = tips(sk, rotations, weights)
    np.testing.assert_allclose(tip[0], tf.quat_rotate(half, [ARM_M, 0.0, 0.0]), atol=1e-12)
    clips = [held("anchor", rotations[0, 0]), held("plus", half), held("minus", -half)]
    baked = bake(sk, clips, 30)
    layers = empty_layers(2, 3)
    layers[:, :, CLIP] = [0, 1, 2]
    layers[:, :, PHASE] = 0.5
    layers[0, :, WEIGHT] = weights[:, 0]
    layers[1, :, WEIGHT] = [1.0, 1e-30, 1e-30]  # now the half turns are negligible: the identity
    proc = AnimationProcessor(gl_context, baked, 3, path=path)
    try:
        proc.resize(2)
        proc.process(layers)
        gpu = proc.read_palette().astype(np.float64)
    finally:
        proc.release()
    assert np.all(np.isfinite(gpu))
    model = reference_palette(baked, layers)
    assert np.max(np.abs(gpu - model)) < 1e-5
    gpu_tips = palette_joint_positions(gpu, sk.inverse_bind)[:, -1]
    np.testing.assert_allclose(gpu_tips[0], tip[0], atol=1e-5)
    np.testing.assert_allclose(gpu_tips[1], [ARM_M, 0.0, 0.0], atol=1e-5)


def test_a_cancelled_sum_falls_back_to_the_anchor_not_nan():
    """Two layers nearly opposite one another, each a hair inside the anchor's hemisphere, at weight 1,
    and the anchor at 1e-30: the aligned sum is 2e-20 long, below CANCELLED_NORM, nothing but rounding
    noise in float32, and the blend takes the anchor's rotation: a valid rotation, every number finite
    (normalising the underflowed sum gave NaN)."""
    sk = arm()
    a = tf.quat_normalize(np.array([1.0, 0.0, 0.0, 1e-20]))
    b = tf.quat_normalize(np.array([-1.0, 0.0, 0.0, 1e-20]))
    anchor = tf.quat_from_axis_angle([0.0, 1.0, 0.0], 0.3)
    anchor = np.array([0.0, anchor[1], 0.0, anchor[3]])
    rotations = np.stack([anchor[None], a[None], b[None]])
    out = tips(sk, rotations, np.array([[1e-30], [1.0], [1.0]]))
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(out[0], tf.quat_rotate(anchor, [ARM_M, 0.0, 0.0]), atol=1e-9)
