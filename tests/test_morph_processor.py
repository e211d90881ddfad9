"""Morph weights on the GPU (issue 23, points 2 and 4): the weight tracks baked beside the joints', and
the processor's per-agent (target, weight) pairs on both paths against the float64 model."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from crowd.anim.bake import bake
from crowd.anim.morph import (ACTIVE_WEIGHT, MORPH_PAIRS, MorphError, active_pairs, bake_morphs, reference_weights,
                              variation_offsets)
from crowd.anim.processor import AnimationProcessor
from crowd.anim.palette_reference import reference_palette
from crowd.anim.processor_inputs import ProcessorError
from crowd.asset.gltf import load_character
from crowd.asset.model import MorphChannel
from crowd.asset.pose import sample_morph_weights
from crowd.frame import CLIP, PHASE, WEIGHT, empty_layers
from crowd.gl import has_compute
from gltf_factory import make_gltf

TARGETS = 9  # more than the MORPH_PAIRS an agent draws
AGENTS = 300


def _character(tmp_path, targets=None):
    """The test strip with TARGETS targets (or `targets`): clip "wave" drives targets 1.. (CUBICSPLINE keys, some
    negative), clip "still" (the same joints) none; target 0 has a default weight."""
    TARGETS = targets or globals()["TARGETS"]  # noqa: N806
    c = load_character(make_gltf(tmp_path, morph=True), scale=1.0)
    rng = np.random.default_rng(3)
    mesh = dataclasses.replace(c.meshes[0], morph_targets=np.arange(TARGETS),
                               morph_positions=rng.normal(0.0, 0.05, (TARGETS, 6, 3)).astype(np.float32),
                               morph_normals=rng.normal(0.0, 0.2, (TARGETS, 6, 3)).astype(np.float32))
    wave = c.clips[0]
    times = wave.channels[0].times
    keys = rng.uniform(-0.3, 1.0, (len(times), 3, TARGETS - 1))
    channel = MorphChannel(np.arange(1, TARGETS), "CUBICSPLINE", times, keys)
    still = dataclasses.replace(wave, name="still", morph_channels=[])
    defaults = np.zeros(TARGETS)
    defaults[0] = 0.25
    return dataclasses.replace(c, meshes=[mesh], clips=[dataclasses.replace(wave, morph_channels=[channel]), still],
                               morphs=tuple(f"t{k}" for k in range(TARGETS)), morph_defaults=defaults).validate()


@pytest.fixture
def morph_character(tmp_path):
    return _character(tmp_path)


def _baked(character, variation=None, seed=7):
    joints = bake(character.skeleton, character.clips)
    joints.morphs = bake_morphs(character, character.clips, joints, variation, seed)
    return joints


def _layers(n, clips, seed=5):
    rng = np.random.default_rng(seed)
    layers = empty_layers(n, 4)
    layers[..., CLIP] = rng.integers(0, clips, (n, 4))
    layers[..., PHASE] = rng.uniform(-2.0, 3.0, (n, 4))
    layers[..., WEIGHT] = np.where(rng.uniform(size=(n, 4)) < 0.3, 0.0, rng.uniform(0.0, 2.0, (n, 4)))
    layers[:10, :, WEIGHT] = 0.0  # no layer counts: the defaults
    return layers


def test_the_tracks_hold_the_clips_weights_at_the_joint_frames(morph_character):
    baked = _baked(morph_character)
    m = baked.morphs
    assert m.names == morph_character.morphs and np.array_equal(m.tracks[0], morph_character.morph_defaults.astype(np.float32))
    wave, still = baked.clips
    assert m.clip_rows[1].tolist() == [0, 1]  # no weight channels: the defaults' row, nothing baked
    first, frames = m.clip_rows[0]
    assert frames == wave.frame_count and m.tracks.shape[0] == 1 + frames
    phases = np.arange(frames) / (frames - 1)
    want = sample_morph_weights(morph_character.morph_defaults, morph_character.clips[0], phases)
    assert np.allclose(m.tracks[first:first + frames], want, atol=1e-6)


def test_nothing_is_baked_where_no_target_moves(tmp_path):
    c = load_character(make_gltf(tmp_path), scale=1.0)
    assert bake_morphs(c, c.clips, bake(c.skeleton, c.clips)) is None  # no targets
    m = load_character(make_gltf(tmp_path / "m", morph=True), scale=1.0)
    still = dataclasses.replace(m, clips=[dataclasses.replace(m.clips[0], morph_channels=[])], morph_defaults=np.zeros(2))
    assert bake_morphs(still, still.clips, bake(still.skeleton, still.clips)) is None  # targets nobody moves
    assert bake_morphs(still, still.clips, bake(still.skeleton, still.clips), {"bulge": (0.0, 0.5)}) is not None


@pytest.mark.parametrize("bad, match", [({"nose": (0, 1)}, "no morph target 'nose'"), ({"bulge": (0.5, 0.2)}, "0 <= lo <= hi <= 1"),
                                        ({"bulge": (0, float("nan"))}, "0 <= lo <= hi <= 1"), ({"bulge": 3}, "two numbers")])
def test_bad_variation_is_refused_in_one_line(tmp_path, bad, match):
    m = load_character(make_gltf(tmp_path, morph=True), scale=1.0)
    with pytest.raises(MorphError, match=match):
        bake_morphs(m, m.clips, bake(m.skeleton, m.clips), bad)


def test_variation_is_fixed_per_agent_and_seed_and_within_its_range(morph_character):
    baked = _baked(morph_character, {"t0": (0.2, 0.6), "t4": (0.0, 0.5)}, seed=11)
    a = variation_offsets(baked.morphs, 0, np.arange(1000))
    assert np.array_equal(a, variation_offsets(baked.morphs, 0, np.arange(1000)))  # deterministic
    assert np.all((a[:, 0] >= 0.2) & (a[:, 0] < 0.6)) and np.all((a[:, 4] >= 0.0) & (a[:, 4] < 0.5))
    assert np.all(a[:, [1, 2, 3, 5, 6, 7, 8]] == 0.0)
    assert np.std(a[:, 0]) > 0.1 and abs(np.corrcoef(a[:, 0], a[:, 4])[0, 1]) < 0.1  # spread, and each target its own
    other = _baked(morph_character, {"t0": (0.2, 0.6), "t4": (0.0, 0.5)}, seed=12)
    assert not np.array_equal(a, variation_offsets(other.morphs, 0, np.arange(1000)))
    assert not np.array_equal(a, variation_offsets(baked.morphs, 1, np.arange(1000)))  # another character's agents differ


def test_active_pairs_keep_the_largest_weights():
    w = np.array([[0.0, 0.5, -0.9, 1e-4, 0.5, 0.2, 0.3, 0.1, 0.05], [0.0] * 9])
    pairs = active_pairs(w)
    assert pairs[0, :, 0].tolist() == [2, 1, 4, 6, 5, 7]  # by size, ties by target; 1e-4 and the 7th largest left out
    assert pairs[0, :, 1].tolist() == [-0.9, 0.5, 0.5, 0.3, 0.2, 0.1]
    assert np.all(pairs[1] == 0.0)
    assert ACTIVE_WEIGHT > 1e-4


def _compare_pairs(gpu, want):
    """Per agent: the same targets with weights within float32's reach (lists compared by target, as a
    tie in size may order two targets either way)."""
    for a, (g, w) in enumerate(zip(gpu, want)):
        gk, wk = g[g[:, 1] != 0], w[w[:, 1] != 0]
        assert len(gk) == len(wk), (a, g, w)
        go, wo = gk[np.argsort(gk[:, 0])], wk[np.argsort(wk[:, 0])]
        assert np.array_equal(go[:, 0], wo[:, 0]), (a, g, w)
        assert np.allclose(go[:, 1], wo[:, 1], atol=2e-6, rtol=0), (a, g, w)
        assert np.all(np.diff(np.abs(g[:len(gk), 1])) <= 0), (a, g)  # largest first


@pytest.mark.parametrize("path", ["compute", "fragment"])
def test_the_processor_writes_each_agents_pairs_and_the_same_joints(gl_context, morph_character, path):
    if path == "compute" and not has_compute(gl_context):
        pytest.skip("no GL 4.3")
    baked = _baked(morph_character, {"t0": (0.2, 0.6), "t4": (0.0, 0.5)})
    layers = _layers(AGENTS, len(baked.clips))
    with AnimationProcessor(gl_context, baked, 4, path=path) as proc:
        proc.resize(AGENTS)
        proc.process(layers)
        assert proc.layout.parts[0].slots == 1
        pairs = proc.read_morph_pairs()
        palette = proc.read_palette()
        assert proc.gpu_bytes()["morphs"] > 0
    want = active_pairs(reference_weights(baked.morphs, baked, layers))
    assert pairs.shape == (AGENTS, MORPH_PAIRS, 2)
    _compare_pairs(pairs, want)
    assert np.count_nonzero(want[:, -1, 1]) > AGENTS // 4  # full lists: the limit is exercised
    ref = reference_palette(baked, layers)
    assert np.max(np.abs(palette[:, :, :, :].astype(np.float64) - ref)) < 1e-5  # the joints as without morphs


def test_without_morphs_there_is_no_slot_and_nothing_allocated(gl_context, morph_character):
    baked = bake(morph_character.skeleton, morph_character.clips)  # no morph bake: the scene moves none
    with AnimationProcessor(gl_context, baked, 4) as proc:
        proc.resize(10)
        proc.process(_layers(10, len(baked.clips)))
        assert proc.layout.parts[0].slots == 0 and proc.gpu_bytes()["morphs"] == 0
        assert proc.read_morph_pairs().shape == (10, 0, 2)


@pytest.mark.parametrize("agent", [-1, 17])
def test_held_weights_replace_the_clips_and_the_variation(gl_context, morph_character, agent):
    """The panel's held weights, on every agent (-1) or one: those targets at exactly that weight."""
    from crowd.anim.morph import ALL_HELD

    baked = _baked(morph_character, {"t0": (0.2, 0.6)})
    layers = _layers(AGENTS, len(baked.clips))
    held = np.full(TARGETS, -1.0)
    held[[0, 5]] = 0.0, 0.75  # t0 held at 0 (off), t5 at 0.75
    with AnimationProcessor(gl_context, baked, 4) as proc:
        proc.resize(AGENTS)
        proc.hold_morphs(0, held, agent)
        proc.process(layers)
        pairs = proc.read_morph_pairs()
        with pytest.raises(ProcessorError, match="at most 1"):
            proc.hold_morphs(0, np.full(TARGETS, 2.0), ALL_HELD)
        with pytest.raises(ProcessorError):
            proc.hold_morphs(0, np.full(TARGETS, np.nan), ALL_HELD)
    want = active_pairs(reference_weights(baked.morphs, baked, layers, held=held, held_agent=agent))
    _compare_pairs(pairs, want)
    rows = slice(None) if agent == ALL_HELD else [agent]
    got = pairs[rows]
    assert np.all(np.any((got[..., 0] == 5) & np.isclose(got[..., 1], 0.75), axis=-1))
    assert not np.any((got[..., 0] == 0) & (got[..., 1] != 0))  # t0 held at 0: never drawn
    if agent != ALL_HELD:
        assert np.any((pairs[:, :, 0] == 0) & (pairs[:, :, 1] != 0))  # the others keep their own t0


def test_the_bake_error_is_found_by_search_and_reported(morph_character):
    """The tracks' largest error against the source's CUBICSPLINE keys: what a dense scan finds, or more;
    a coarse bake says so in its warnings, the default one stays below the bound."""
    from crowd.anim.morph import ERROR_WARN, track_error

    clips = morph_character.clips
    coarse = bake(morph_character.skeleton, clips, 2.0)
    coarse.morphs = bake_morphs(morph_character, clips, coarse)
    error, clip, target, phase = coarse.morphs.error
    # A dense scan of the same difference (the processor's lerp of the stored frames against the keys).
    m = coarse.morphs
    first, frames = m.clip_rows[0]
    p = np.linspace(0.0, 1.0, 20001)
    f = p * (frames - 1)
    i0 = np.clip(np.floor(f), 0, frames - 2).astype(int)
    track = m.tracks[first:first + frames].astype(np.float64)
    baked = track[i0] + (track[i0 + 1] - track[i0]) * (f - i0)[:, None]
    scan = np.max(np.abs(baked - sample_morph_weights(morph_character.morph_defaults, clips[0], p)))
    assert error >= scan - 1e-9 and error > ERROR_WARN and clip == "wave"
    assert any("morph weights baked at" in w for w in coarse.warnings)
    fine = _baked(morph_character)
    assert fine.morphs.error == track_error(fine.morphs, morph_character, clips, fine)
    assert fine.morphs.error[0] < coarse.morphs.error[0]


@pytest.mark.parametrize("path", ["compute", "fragment"])
def test_a_character_of_a_thousand_targets_runs_on_both_paths(gl_context, tmp_path, path):
    """MAX_MORPHS targets: nothing per target lives in uniforms (a compute shader need hold only 512
    components), so the processor compiles and writes the same pairs as its float64 model."""
    from crowd.asset.model import MAX_MORPHS

    if path == "compute" and not has_compute(gl_context):
        pytest.skip("no GL 4.3")
    character = _character(tmp_path, MAX_MORPHS)
    baked = _baked(character, {"t0": (0.2, 0.6), "t999": (0.0, 1.0)})
    layers = _layers(40, len(baked.clips))
    held = np.full(MAX_MORPHS, -1.0)
    held[1000] = 0.5
    with AnimationProcessor(gl_context, baked, 4, path=path) as proc:
        proc.resize(40)
        proc.hold_morphs(0, held, 3)
        proc.process(layers)
        pairs = proc.read_morph_pairs()
    _compare_pairs(pairs, active_pairs(reference_weights(baked.morphs, baked, layers, held=held, held_agent=3)))
