"""Stiff and extreme cases of the animation pipeline, each measured on the GPU against the float64
reference (crowd.anim.accuracy's 3 cm shell error) and judged against a stated bound.

Contract: ``run_cases(ctx, character, interpolation, fps, precision)`` → list of
``{"case", "max_error_mm", "bound_mm", "passed", "detail", "checks_passed"}``, one per case, in this
order (``precision`` is a storage name: f32, f16, compressed or compressed@<bound in mm>):

- antipodal blends: a clip blended with itself stored as -q (the same rotations, opposite signs);
- equal-weight opposite rotations: +θ and -θ blended 50/50, θ swept from 0 to 180°;
- 64-joint chains: random 2 to 4 layer blends of a 64-joint, 3.2 m chain, on both processor paths;
- 256-joint chains: the same for 256 joints (the most a skeleton may have), 3.2 m long;
- keys up to a half turn apart: a root turning 30 to 170 degrees from one 30 fps key to the next;
- joint scale 1e-4 and 1e4: an arm with its elbow scaled by each, while the root turns;
- phase near 1.0: every clip at phases a float32 ulp from 0 and 1, and at 1 and 2 exactly;
- 10 hours of play: the AI's phase accumulator after 2,160,000 substeps of 1/60 s;
- dt spikes: the crowd AI through frame times of 0, 1 µs, 0.25 s, 3 s and 10,000 s.

Bounds come from the float32 analysis in tests/test_processor.py (a few roundings of 6e-8 per level
of the hierarchy, relative to the chain's length) or, where the case goes through interpolation, from
the default configuration's target of 1 mm. On a compressed bake every bound grows by the compression
bound: the compressor keeps every key within it (crowd.anim.compress), on any skeleton.
"""

from __future__ import annotations

import time
from fractions import Fraction

import numpy as np

from crowd.anim import accuracy
from crowd import transforms as tf
from crowd.anim.bake import COMPRESSED, DEFAULT_BOUND_MM, bake
from crowd.asset.model import Channel, Clip, Skeleton
from crowd.frame import CLIP, PHASE, WEIGHT, empty_layers
from crowd.gl import has_compute

TARGET_MM = 1.0  # the default configuration's max shell error on the built-in zombie
NUMERIC_MM = 0.01  # float32 arithmetic alone on a skeleton of a few joints, well inside 1 m
CHAIN_MM = 0.2  # 64 levels: D * 4 * eps * |p| = 64 * 4 * 6e-8 * 6.4 m ≈ 0.1 mm, doubled
LONG_CHAIN_MM = 0.8  # 256 levels of a chain as long: four times that
ROUNDINGS = 32 * 2.0 ** -24  # a few float32 roundings per level, relative to the size they round (scale cases)
AMBIGUOUS_DEG = 0.01  # within this of 90°, +θ and -θ have two equally near blends (identity or 180°)


def parse_storage(storage: str) -> tuple[str, float]:
    """(precision, compression bound in mm) of a storage name: "f32", "f16", "compressed" (the default
    bound) or "compressed@0.1" (a bound of 0.1 mm)."""
    precision, _, bound = storage.partition("@")
    if precision != COMPRESSED:
        if bound:
            raise ValueError(f"storage {storage!r}: only {COMPRESSED} takes a bound (compressed@0.1)")
        return precision, DEFAULT_BOUND_MM
    try:
        return precision, float(bound) if bound else DEFAULT_BOUND_MM
    except ValueError:
        raise ValueError(f"storage {storage!r}: the bound after @ must be a number of millimetres") from None


def bake_storage(skeleton, clips, fps, storage: str):
    """The bake of `clips` at `fps` in a storage name's precision and bound (parse_storage)."""
    precision, bound_mm = parse_storage(storage)
    return bake(skeleton, clips, fps, precision, bound_mm=bound_mm)


def _case(name: str, errors_m, bound_mm: float, detail: str, ok: bool = True) -> dict:
    e = float(np.max(errors_m)) * 1e3 if np.size(errors_m) else 0.0
    finite = bool(np.all(np.isfinite(errors_m)))
    return {"case": name, "max_error_mm": e if finite else float("inf"), "bound_mm": bound_mm,
            "passed": bool(finite and ok and e <= bound_mm), "detail": detail, "checks_passed": bool(finite and ok)}


def _arm(joints: int = 4, length: float = 0.3) -> Skeleton:
    """A straight chain along +X from the origin: the root turns, the rest lever the error out."""
    parents = np.arange(-1, joints - 1, dtype=np.int32)
    rest_t = np.tile([length, 0.0, 0.0], (joints, 1))
    rest_t[0] = 0.0
    glob = np.tile(np.eye(4), (joints, 1, 1))
    glob[:, 0, 3] = np.arange(joints) * length
    return Skeleton(tuple(f"arm{j}" for j in range(joints)), parents, rest_t, np.tile([0.0, 0.0, 0.0, 1.0], (joints, 1)),
                    np.ones((joints, 3)), np.linalg.inv(glob))


def _held(name: str, q: np.ndarray, duration: float = 0.1) -> Clip:
    """A clip holding the root at rotation q (two equal keys)."""
    times = np.array([0.0, duration])
    return Clip(name, [Channel(0, "rotation", "LINEAR", times, np.stack([q, q]))], 0.0, duration, False)


def _gpu_error(ctx, skeleton, clips, layers, interpolation, fps, precision, path="auto", masks=None):
    baked = bake_storage(skeleton, clips, fps, precision)
    truth = accuracy.truth(skeleton, clips, layers, masks)
    return accuracy.measure_gpu(ctx, skeleton, baked, layers, truth, interpolation, path, masks)


def antipodal_blends(ctx, character, interpolation, fps, precision) -> dict:
    """Every clip of the character next to a copy whose rotation keys are all negated (the same
    animation). Blended at equal weights, and with either copy a hair heavier, the result must be the
    clip itself, never a collapse of the rotation toward zero."""
    clips = list(character.clips)
    negated = [Clip(c.name + "_negated", [Channel(ch.joint, ch.path, ch.interpolation, ch.times, -ch.values if ch.path == "rotation" else ch.values)
                                          for ch in c.channels], c.start, c.duration, c.loop) for c in clips]
    n_per = 64
    rng = np.random.default_rng(1)
    c = len(clips)
    layers = empty_layers(c * n_per, 2)
    layers[:, 0, CLIP] = np.repeat(np.arange(c), n_per)
    layers[:, 1, CLIP] = layers[:, 0, CLIP] + c
    layers[:, :, PHASE] = rng.uniform(0.0, 1.0, c * n_per)[:, None]
    layers[:, :, WEIGHT] = 0.5
    layers[0::3, 1, WEIGHT] = 0.5 + 1e-3
    layers[1::3, 0, WEIGHT] = 0.5 + 1e-3
    all_clips = clips + negated
    baked = bake_storage(character.skeleton, all_clips, fps, precision)
    blended = accuracy.gpu_palette(ctx, baked, layers, interpolation)
    alone = layers.copy()
    alone[:, 1, WEIGHT] = 0.0
    points = accuracy.shell_points(character.skeleton)
    err = accuracy.shell_error(blended, accuracy.truth(character.skeleton, all_clips, layers), points)
    same = float(np.max(accuracy.shell_error(blended, accuracy.gpu_palette(ctx, baked, alone, interpolation), points))) * 1e3
    return _case("antipodal blends", err, TARGET_MM,
                 f"{c} clips of the zombie each blended with its own keys negated, {c * n_per} poses, equal weights and either side "
                 f"heavier; against the clip alone on the GPU: {same:.1e} mm (bound {NUMERIC_MM} mm)", ok=same <= NUMERIC_MM)


def opposite_rotations(ctx, interpolation, fps, precision) -> dict:
    """+θ and -θ about one axis at equal weights. Below 90° the blend is the identity, above it the
    aligned quaternions add up to a half turn; at exactly 90° both are equally right, so poses within
    AMBIGUOUS_DEG of it are left out (and counted)."""
    skeleton = _arm()
    theta = np.radians(np.linspace(0.0, 180.0, 721))
    keep = np.abs(np.degrees(theta) - 90.0) > AMBIGUOUS_DEG
    theta = theta[keep]
    axis = tf.quat_normalize(np.array([1.0, 0.3, -0.2, 0.0]))[:3]
    clips = []
    for k, t in enumerate(theta):
        clips += [_held(f"plus{k}", tf.quat_from_axis_angle(axis, t)), _held(f"minus{k}", tf.quat_from_axis_angle(axis, -t))]
    layers = empty_layers(len(theta), 2)
    layers[:, 0, CLIP] = 2 * np.arange(len(theta))
    layers[:, 1, CLIP] = 2 * np.arange(len(theta)) + 1
    layers[:, :, PHASE] = 0.5
    layers[:, :, WEIGHT] = 1.0
    err = _gpu_error(ctx, skeleton, clips, layers, interpolation, fps, precision)
    return _case("equal-weight opposite rotations", err, NUMERIC_MM,
                 f"θ from 0 to 180° in 0.25° steps on a 4-joint, 0.9 m arm ({int(np.count_nonzero(~keep))} pose within "
                 f"{AMBIGUOUS_DEG}° of 90° left out: identity and a half turn are equally right there)")


def chain_character(joints: int = 64, length: float = 0.05, fps: int = 30):
    """A chain along +Y keyed at `fps`, every joint bending and twisting a few degrees: a wave clip
    (loop) and a curl clip (one-shot)."""
    parents = np.arange(-1, joints - 1, dtype=np.int32)
    rest_t = np.tile([0.0, length, 0.0], (joints, 1))
    rest_t[0] = 0.0
    glob = np.tile(np.eye(4), (joints, 1, 1))
    glob[:, 1, 3] = np.arange(joints) * length
    skeleton = Skeleton(tuple(f"j{j:02d}" for j in range(joints)), parents, rest_t, np.tile([0.0, 0.0, 0.0, 1.0], (joints, 1)),
                        np.ones((joints, 3)), np.linalg.inv(glob))
    times = np.arange(2 * fps + 1) / fps
    z, y, x = (np.array(v) for v in ([0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]))
    wave, curl = [], []
    for j in range(joints):
        bend = np.sin(np.pi * times + j * 0.2) * np.radians(6.0)
        twist = np.cos(np.pi * times + j * 0.1) * np.radians(9.0)
        wave.append(Channel(j, "rotation", "LINEAR", times, tf.quat_mul(tf.quat_from_axis_angle(z, bend), tf.quat_from_axis_angle(y, twist))))
        curl.append(Channel(j, "rotation", "LINEAR", times, tf.quat_from_axis_angle(x, np.radians(5.0) * times / times[-1])))
    return skeleton, [Clip("wave", wave, 0.0, float(times[-1]), True), Clip("curl", curl, 0.0, float(times[-1]), False)]


def long_chains(ctx, interpolation, fps, precision, joints: int = 64) -> dict:
    skeleton, clips = chain_character(joints, 3.2 / joints)
    rng = np.random.default_rng(3)
    samples = accuracy.draw_samples(clips, rng, 50, 300)
    worst = 0.0
    for path in ("compute", "fragment") if has_compute(ctx) else ("fragment",):
        err = _gpu_error(ctx, skeleton, clips, samples.layers, interpolation, fps, precision, path)
        worst = max(worst, float(np.max(err)))
    return _case(f"{joints}-joint chains", np.array([worst]), CHAIN_MM if joints <= 64 else LONG_CHAIN_MM,
                 f"a {joints}-joint, 3.2 m chain keyed at 30 fps, {len(samples.layers)} single and 2-4 layer poses, compute and fragment paths")


def half_turn_keys(ctx, interpolation, fps, precision) -> dict:
    """The root of a 0.9 m arm turning by 30, 60, 90, 120, 150 and 170 degrees from one 30 fps key to the
    next, sampled at 64 phases between them, against slerp. Bound: the arm's reach times the largest
    rotation error of qt_corrected's weight for keys a half turn apart (1.2e-3 rad, searched for in
    tests/test_processor.py), plus float32's share; plain nlerp is 0.14 rad off there and fails it."""
    skeleton = _arm()
    axis = tf.quat_normalize(np.array([0.2, 0.3, 1.0, 0.0]))[:3]
    steps = np.radians([30.0, 60.0, 90.0, 120.0, 150.0, 170.0])
    key_fps = 30.0
    clips = [Clip(f"turn{int(round(np.degrees(a)))}", [Channel(0, "rotation", "LINEAR", np.array([0.0, 1.0 / key_fps]),
                                                                np.stack([tf.quat_from_axis_angle(axis, 0.0), tf.quat_from_axis_angle(axis, a)]))],
                  0.0, 1.0 / key_fps, False) for a in steps]
    phases = np.linspace(0.0, 1.0, 64)
    layers = empty_layers(len(clips) * len(phases), 1)
    layers[:, 0, CLIP] = np.repeat(np.arange(len(clips)), len(phases))
    layers[:, 0, PHASE] = np.tile(phases, len(clips))
    layers[:, 0, WEIGHT] = 1.0
    err = _gpu_error(ctx, skeleton, clips, layers, interpolation, fps, precision)
    reach_mm = (0.9 + accuracy.SHELL_M) * 1e3
    return _case("keys up to a half turn apart", err, 1.2e-3 * reach_mm + NUMERIC_MM,
                 f"a 0.9 m arm's root turning {', '.join(f'{np.degrees(a):.0f}' for a in steps)}° between two keys, 64 phases each")


def scale_extremes(ctx, interpolation, fps, precision) -> dict:
    """A 4-joint arm whose second joint is held at scale 1e-4, then 1e4 (its children's offsets and their
    shell points scale with it), while the root turns 40 degrees over a second. Bound: NUMERIC_MM plus
    ROUNDINGS per level of the scaled arm's reach (float32 rounds relative to the sizes involved)."""
    worst, details = (0.0, 1.0, 0.0), []  # (error over bound, bound, error) of the scale nearest its bound
    for scale in (1e-4, 1e4):
        skeleton = _arm()
        turn = Channel(0, "rotation", "LINEAR", np.array([0.0, 1.0]),
                       np.stack([tf.quat_from_axis_angle([0.0, 0.0, 1.0], 0.0), tf.quat_from_axis_angle([0.0, 0.0, 1.0], np.radians(40.0))]))
        held = Channel(1, "scale", "LINEAR", np.array([0.0, 1.0]), np.full((2, 3), scale))
        clip = Clip("scaled", [turn, held], 0.0, 1.0, False)  # one-shot: a loop would close from 40 degrees back to 0
        layers = empty_layers(97, 1)
        layers[:, 0, PHASE] = np.linspace(0.0, 1.0, 97)
        layers[:, 0, WEIGHT] = 1.0
        err = _gpu_error(ctx, skeleton, [clip], layers, interpolation, fps, precision)
        reach_mm = (0.3 + (0.6 + accuracy.SHELL_M) * max(scale, 1.0)) * 1e3
        bound = NUMERIC_MM + ROUNDINGS * 4 * reach_mm
        e = float(np.max(err)) * 1e3
        worst = max(worst, (e / bound, bound, e))
        details.append(f"scale {scale:g}: {e:.3g} mm (bound {bound:.3g} mm)")
    return _case("joint scale 1e-4 and 1e4", np.array([worst[2] * 1e-3]), worst[1],
                 "an arm's elbow held at each scale while the root turns; the one nearest its bound is reported: " + "; ".join(details))


def phase_near_one(ctx, character, interpolation, fps, precision) -> dict:
    ulp = np.float32(2.0 ** -24)
    phases = np.array([0.0, ulp, 1.0 - ulp, 1.0 - 2 * ulp, 1.0, 1.0 + 2 * ulp, 2.0, -ulp], np.float32)
    c = len(character.clips)
    layers = empty_layers(c * len(phases), 1)
    layers[:, 0, CLIP] = np.repeat(np.arange(c), len(phases))
    layers[:, 0, PHASE] = np.tile(phases, c)
    layers[:, 0, WEIGHT] = 1.0
    err = _gpu_error(ctx, character.skeleton, list(character.clips), layers, interpolation, fps, precision)
    return _case("phase near 1.0", err, TARGET_MM,
                 "every zombie clip (looping and one-shot) at phases 0, 2^-24, 1 - 2^-24, 1 - 2^-23, 1, 1 + 2^-23, 2 and -2^-24")


def ten_hours(ctx, character, interpolation, fps, precision, hours: float = 10.0) -> dict:
    """The AI keeps each agent's phase as a wrapped float64 (crowd.sim.locomotion.advance_phase). Step it as the
    AI does for `hours` of 1/60 s substeps, at each looping clip's rate, and compare the pose with the
    pose at the exact phase (rational arithmetic). The naive float32 clock (seconds summed per step,
    phase = time / duration) is measured alongside, as the detail says."""
    from crowd.sim.locomotion import advance_phase

    h = 1.0 / 60.0
    steps = int(round(hours * 3600.0 / h))
    loops = [i for i, c in enumerate(character.clips) if c.loop]
    speeds = np.array([0.8, 1.0, 1.3])  # playback speeds, as the AI's per-agent speed factors give
    clip_of = np.repeat(loops, len(speeds))
    rate = np.tile(speeds, len(loops)) / np.array([character.clips[i].duration for i in clip_of])
    step = rate * h
    phase = np.zeros_like(step)
    for _ in range(steps):
        advance_phase(phase, step)
    exact = np.array([float((Fraction(float(s)) * steps) % 1) for s in step])
    clock = np.cumsum(np.full(steps, np.float32(h), np.float32), dtype=np.float32)[-1]  # sequential float32 sum
    naive = np.mod(clock.astype(np.float64) * rate, 1.0)
    layers = empty_layers(3 * len(step), 1)
    layers[:, 0, CLIP] = np.tile(clip_of, 3)
    layers[:, 0, WEIGHT] = 1.0
    layers[:, 0, PHASE] = np.concatenate([phase, exact, naive]).astype(np.float32)
    truth_layers = layers.copy()
    truth_layers[:, 0, PHASE] = np.tile(exact, 3).astype(np.float32)
    baked = bake_storage(character.skeleton, list(character.clips), fps, precision)
    truth = accuracy.truth(character.skeleton, list(character.clips), truth_layers)
    err = accuracy.measure_gpu(ctx, character.skeleton, baked, layers, truth, interpolation)
    n = len(step)
    ours, naive_err = err[:n], err[2 * n:]
    gap = np.abs(phase - exact)
    phase_err = float(np.max(np.minimum(gap, 1.0 - gap)))  # around the circle: 0.9999… and 0 are neighbours
    return _case(f"clip time after {hours:g} hours of play", ours, TARGET_MM,
                 f"{steps:,} substeps of 1/60 s at {len(loops)} looping clips x 3 speeds: phase error {phase_err:.1e} cycles; "
                 f"a float32 clock of summed frame times would be off by {float(clock) - hours * 3600.0:+.0f} s and "
                 f"{float(np.max(naive_err)) * 1e3:.0f} mm")


def dt_spikes(ctx, character, interpolation, fps, precision, agents: int = 200) -> dict:
    """The crowd AI through frame times of 0, 1 µs, 0.25 s, 3 s and 10,000 s between normal frames.
    The AI clamps a frame to max_dt and substeps it, so each spike must move no agent farther than its
    top speed allows, keep every invariant, and give poses as accurate as any other frame."""
    from crowd.sim.ai import CrowdAI
    from crowd.sim.config import AIConfig
    from crowd.sim.motion import motion_for, upper_body_mask
    from crowd.anim.roles import bake_roles, match_roles

    roles, _ = match_roles(character.clips)
    baked = bake_roles(character, roles, fps, *parse_storage(precision))
    clips = [character.clip(c.name) for c in baked.clips]
    masks = upper_body_mask(character.skeleton)
    config = AIConfig()
    ai = CrowdAI(agents, 5, motion_for(character, baked, roles), config)
    frames = [1 / 60] * 20 + [0.0, 1e-6, 1 / 60, 0.25, 1 / 60, 3.0, 1 / 60, 1e4] + [1 / 60] * 20
    worst, faults, jump = 0.0, [], 0.0
    top_speed = float(np.max(ai.walk_top)) + ai.motion.run_speed * float(np.max(ai.speed_factor))
    for dt in frames:
        x0, z0 = ai.x.copy(), ai.z.copy()
        ai.step(dt)
        faults += ai.check()
        allowed = top_speed * min(dt, config.max_dt) + config.separation_radius  # separation may push by up to a radius
        jump = max(jump, float(np.max(np.hypot(ai.x - x0, ai.z - z0) - allowed)) if agents else 0.0)
        layers = ai.layers()
        if dt >= 0.25 or dt == 0.0:
            truth = accuracy.truth(character.skeleton, clips, layers, masks)
            err = accuracy.measure_gpu(ctx, character.skeleton, baked, layers, truth, interpolation, masks=masks)
            worst = max(worst, float(np.max(err)))
    detail = f"{agents} agents; frame times 0, 1e-6, 0.25, 3 and 10,000 s among 1/60 s frames; max_dt {config.max_dt} s"
    detail += f"; AI faults: {sorted(set(faults)) or 'none'}; largest move beyond top speed x dt + separation: {max(jump, 0.0) * 1e3:.1f} mm"
    return _case("dt spikes", np.array([worst]), TARGET_MM, detail, ok=not faults and jump <= 1e-9)


def run_cases(ctx, character, interpolation: str, fps, precision: str, hours: float = 10.0, progress=None) -> list[dict]:
    """Every case for one configuration; `precision` is a storage name (parse_storage). A compressed
    bake may move every key by up to its bound, so each case's bound grows by that much there.
    `progress(line)`, when given, hears each case's name and seconds as it finishes."""
    steps = [
        lambda: antipodal_blends(ctx, character, interpolation, fps, precision),
        lambda: opposite_rotations(ctx, interpolation, fps, precision),
        lambda: long_chains(ctx, interpolation, fps, precision),
        lambda: long_chains(ctx, interpolation, fps, precision, joints=256),
        lambda: half_turn_keys(ctx, interpolation, fps, precision),
        lambda: scale_extremes(ctx, interpolation, fps, precision),
        lambda: phase_near_one(ctx, character, interpolation, fps, precision),
        lambda: ten_hours(ctx, character, interpolation, fps, precision, hours),
        lambda: dt_spikes(ctx, character, interpolation, fps, precision),
    ]
    cases = []
    for step in steps:
        start = time.perf_counter()
        cases.append(step())
        if progress is not None:
            progress(f"stability ({precision}, {interpolation}): {cases[-1]['case']} in {time.perf_counter() - start:.1f} s")
    kind, bound_mm = parse_storage(precision)
    if kind == COMPRESSED:
        for case in cases:
            case["bound_mm"] += bound_mm
            case["passed"] = case["checks_passed"] and case["max_error_mm"] <= case["bound_mm"]
            case["detail"] += f"; bound raised by the compression bound, {bound_mm:g} mm"
    return cases
