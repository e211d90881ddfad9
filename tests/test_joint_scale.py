"""Joint scale (issue 44, point 1): uniform scale runs down the chains; non-uniform scale sits only on a
joint's own skinning matrix (``AnimationBake.residual``), so a leaf is drawn exactly, a joint with children
exactly on its own vertices, with one warning naming it and how far its children are; both processor
paths agree with the float64 twin, and the twin with glTF's meaning; a character without non-uniform
scale has no residual texture and no code for it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from crowd.anim import reference
from crowd.anim.bake import bake
from crowd.anim.palette_reference import reference_palette
from crowd.anim.processor import AnimationProcessor
from crowd.asset.gltf import load_character
from crowd.frame import CLIP, MASK, PHASE, WEIGHT
from gltf_factory import KEY_TIMES, add_channel, make_gltf

LEAF, INNER = 3, 2  # the factory chain's tip and mid nodes
STRETCH = np.array([[1.0, 1.0, 1.0], [2.0, 1.0, 1.0], [1.0, 0.5, 1.5]])


def _scaled(tmp_path, node: int, keys: np.ndarray):
    path = make_gltf(tmp_path)
    doc = json.loads(path.read_text())
    add_channel(doc, node, "scale", keys)
    path.write_text(json.dumps(doc))
    return load_character(path, scale=1.0)


def _at_keys(character, baked):
    """(twin's skinned vertices, glTF's) at each key, float64, metres."""
    clip, mesh = character.clips[0], character.meshes[0]
    phases = (KEY_TIMES - clip.start) / clip.duration
    layers = np.zeros((len(phases), 4, 4), np.float32)
    layers[:, :, MASK] = -1
    layers[:, 0, PHASE], layers[:, 0, WEIGHT] = phases, 1.0
    rows = reference_palette(baked, layers)
    truth = reference.skinning_matrices(character.skeleton, reference.sample_clip(character.skeleton, clip, phases))
    twin = np.concatenate([rows, np.tile([0.0, 0.0, 0.0, 1.0], rows.shape[:2] + (1, 1))], axis=2)
    return (reference.skin_points(twin, mesh.positions, mesh.joints, mesh.weights),
            reference.skin_points(truth, mesh.positions, mesh.joints, mesh.weights))


def test_non_uniform_scale_on_a_leaf_is_drawn_as_gltf_says(tmp_path):
    c = _scaled(tmp_path, LEAF, STRETCH)
    baked = bake(c.skeleton, c.clips, fps=120)
    assert baked.residual is not None and not any("non-uniform" in w for w in baked.warnings)
    twin, truth = _at_keys(c, baked)
    assert np.abs(twin - truth).max() <= 1e-4  # 0.1 mm, the bound (float64: about 1e-8)


def test_uniform_scale_down_a_chain_is_exact_and_pays_for_no_residual(tmp_path):
    c = _scaled(tmp_path, INNER, np.repeat([[1.0], [1.5], [2.0]], 3, axis=1))
    baked = bake(c.skeleton, c.clips, fps=120)
    assert baked.scale is not None and baked.residual is None
    twin, truth = _at_keys(c, baked)
    assert np.abs(twin - truth).max() <= 1e-9
    unscaled = load_character(make_gltf(tmp_path / "plain"), scale=1.0)
    plain = bake(unscaled.skeleton, unscaled.clips)
    assert plain.scale is None and plain.residual is None


def test_non_uniform_scale_on_a_joint_with_children_is_named_with_its_error(tmp_path):
    c = _scaled(tmp_path, INNER, STRETCH)
    baked = bake(c.skeleton, c.clips, fps=120)
    (line,) = [w for w in baked.warnings if "non-uniform" in w]
    assert line.startswith("joint 'mid': non-uniform scale on a joint with children") and " mm from glTF's pose (clip 'wave')" in line
    twin, truth = _at_keys(c, baked)
    mesh = c.meshes[0]
    own = np.flatnonzero((mesh.joints[:, 0] == 1) & (mesh.weights[:, 0] >= 0.999))  # (wholly on 'mid')
    if own.size:  # a vertex wholly on the joint itself is drawn as glTF says
        assert np.abs(twin[:, own] - truth[:, own]).max() <= 1e-4
    assert np.abs(twin - truth).max() > 0.01  # its children's are not: that is what the warning says


@pytest.mark.parametrize("path", ["compute", "fragment"])
def test_both_processor_paths_agree_with_the_twin(gl_context, tmp_path, path):
    from crowd.gl import has_compute

    if path == "compute" and not has_compute(gl_context):
        pytest.skip("no GL 4.3")
    for node in (LEAF, INNER):
        c = _scaled(tmp_path / str(node), node, STRETCH)
        baked = bake(c.skeleton, c.clips, fps=120)
        rng = np.random.default_rng(node)
        n = 64
        layers = np.zeros((n, 4, 4), np.float32)
        layers[:, :, MASK] = -1
        layers[:, 0, PHASE], layers[:, 0, WEIGHT] = rng.uniform(0, 1, n), 1.0
        layers[:, 1, PHASE], layers[:, 1, WEIGHT] = rng.uniform(0, 1, n), rng.uniform(0, 1, n)
        with AnimationProcessor(gl_context, baked, 4, path=path) as proc:
            proc.resize(n)
            proc.process(layers)
            gpu = proc.read_palette()
            assert proc.gpu_bytes()["animation"] >= baked.residual.nbytes
        assert np.abs(gpu[:, :, :3, :] - reference_palette(baked, layers)).max() <= 1e-5


@pytest.mark.parametrize("path", ["compute", "fragment"])
def test_a_cast_with_and_without_non_uniform_scale(gl_context, tmp_path, path):
    """The fragment path's fourth scratch plane and the residual's unit, with a character that has neither
    drawn before and after the one that has them."""
    from crowd.anim.roles import bake_roles, match_roles
    from crowd.gl import has_compute

    if path == "compute" and not has_compute(gl_context):
        pytest.skip("no GL 4.3")
    zombie = load_character(None)
    plain = bake_roles(zombie, match_roles(zombie.clips)[0])
    c = _scaled(tmp_path, LEAF, STRETCH)
    scaled = bake(c.skeleton, c.clips, fps=120)
    n = 16
    layers = np.zeros((2 * n, 4, 4), np.float32)
    layers[:, :, MASK] = -1
    layers[:, 0, PHASE], layers[:, 0, WEIGHT] = np.random.default_rng(3).uniform(0, 1, 2 * n), 1.0
    for cast in ((plain, scaled), (scaled, plain)):
        with AnimationProcessor(gl_context, list(cast), 4, path=path) as proc:
            proc.resize([n, n])
            proc.process(layers)
            gpu = proc.read_palette()
        k = cast.index(scaled)
        mine = gpu[k * n:(k + 1) * n, :scaled.joint_count, :3, :]
        assert np.abs(mine - reference_palette(scaled, layers[k * n:(k + 1) * n])).max() <= 1e-5
