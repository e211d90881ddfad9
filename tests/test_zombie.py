import numpy as np
import pygltflib
import pytest

from conftest import khronos_issues
from crowd.anim import reference
from crowd.asset.gltf_write import glb_bytes
from crowd.asset.zombie import ASSET_PATH, build_character
from crowd.asset.rig import SOCKET_JOINT

REQUIRED_JOINTS = {"hips", "spine", "chest", "neck", "head"} | {
    f"{p}_{s}" for p in ("upper_arm", "forearm", "hand", "thigh", "shin", "foot") for s in "lr"}


@pytest.fixture(scope="module")
def generated():
    return build_character()


@pytest.fixture(scope="module")
def as_written():
    """The shipped file's meshes as the generator wrote them (loading merges those that share a draw)."""
    from crowd.asset.gltf import load_character

    return load_character(merge=False)


def test_committed_glb_is_what_the_generator_writes(generated):
    assert ASSET_PATH.read_bytes() == glb_bytes(generated), "assets/zombie.glb is stale: run python -m crowd.asset.zombie"


def test_skeleton(zombie):
    names = set(zombie.skeleton.names)
    assert len(names) >= 20 and REQUIRED_JOINTS <= names
    assert zombie.sockets == {"weapon_r": zombie.skeleton.index(SOCKET_JOINT)}
    assert zombie.skeleton.names[zombie.skeleton.parents[zombie.sockets["weapon_r"]]] == "hand_r"


def test_meshes_lods_and_pieces(as_written):
    tris = {}
    for m in as_written.meshes:
        tris.setdefault(m.lod, {})[m.piece] = m.triangle_count
        assert m.weights.shape[1] == 4
        np.testing.assert_allclose(m.weights.sum(1), 1.0, atol=1e-6)
        assert np.all(m.weights >= 0)
    assert set(tris) == {0, 1, 2, 3, 4}
    assert tris[4] == {"body": 16}  # LOD4: the shadow proxy, one column
    default = lambda lod: tris[lod]["body"] + tris[lod]["head_a"] + tris[lod]["shirt_torn"]
    assert default(0) >= 3000
    assert 0.18 < default(1) / default(0) < 0.32  # about 1/4
    assert 0.04 < default(2) / default(0) < 0.09  # about 1/16
    # LOD3: each head choice's whole figure merged into one mesh under the head's piece name.
    assert set(tris[3]) == {"head_a", "head_b"} and 0.02 < tris[3]["head_a"] / default(0) < 0.035  # about 1/39
    assert {"head_a", "head_b"} <= set(tris[0]) and "shirt_torn" in tris[0]


def test_skin_weights_are_smooth(as_written):
    """Along every edge of the body only part of the weight moves between joints: no rigid seams."""
    body = next(m for m in as_written.meshes if m.piece == "body" and m.lod == 0)
    dense = np.zeros((body.positions.shape[0], as_written.skeleton.joint_count))
    for k in range(4):
        np.add.at(dense, (np.arange(dense.shape[0]), body.joints[:, k].astype(np.int64)), body.weights[:, k])
    edges = body.indices.reshape(-1, 3)[:, [0, 1]]
    moved = 0.5 * np.abs(dense[edges[:, 0]] - dense[edges[:, 1]]).sum(1)  # weight handed from joint to joint
    assert moved.max() < 0.95  # 1.0 would be a rigid seam
    assert np.percentile(moved, 99) < 0.6
    assert np.mean(body.weights[:, 1] > 0.05) > 0.15  # a good share of vertices blend two or more joints


def test_clips(zombie):
    clips = {c.name: c for c in zombie.clips}
    assert {"idle", "shamble", "run", "attack", "hit", "death", "crawl"} <= set(clips)
    assert not clips["death"].loop and clips["shamble"].loop
    for name in ("shamble", "run"):
        markers = clips[name].markers
        assert set(markers) == {"left_foot_down", "right_foot_down"}
        assert markers["right_foot_down"] == pytest.approx((markers["left_foot_down"] + 0.5) % 1.0)
        assert clips[name].stride > 0
    # Real motion: each clip moves the hands or feet by a good fraction of a metre.
    sk = zombie.skeleton
    ends = [sk.index(n) for n in ("hand_l", "hand_r", "foot_l", "foot_r", "head")]
    for clip in zombie.clips:
        g = reference.global_matrices(sk, reference.sample_clip(sk, clip, np.linspace(0, 1, 24)))
        span = np.ptp(g[:, ends, :3, 3], axis=0).max()
        assert span > 0.25, f"{clip.name} barely moves ({span:.3f} m)"


def test_locomotion_feet_plant_at_markers(zombie):
    sk = zombie.skeleton
    left, right = sk.index("foot_l"), sk.index("foot_r")
    for name in ("shamble", "run"):
        clip = zombie.clip(name)
        down = np.array([clip.markers["left_foot_down"], clip.markers["right_foot_down"]])
        g = reference.global_matrices(sk, reference.sample_clip(sk, clip, down))
        # At its heel strike a foot is on the ground and ahead of the other one.
        assert g[0, left, 2, 3] > g[0, right, 2, 3] + 0.1, name
        assert g[1, right, 2, 3] > g[1, left, 2, 3] + 0.1, name


def test_death_ends_lying_down(zombie):
    sk = zombie.skeleton
    g = reference.global_matrices(sk, reference.sample_clip(sk, zombie.clip("death"), np.array([1.0])))
    assert g[0, sk.index("head"), 1, 3] < 0.4


def test_props_have_grip_frames(zombie):
    assert set(zombie.props) == {"pipe", "axe"}
    for prop in zombie.props.values():
        assert prop.mesh.triangle_count > 50
        assert prop.grip.shape == (4, 4) and np.allclose(prop.grip[3], [0, 0, 0, 1])


def test_props_have_a_mesh_per_body_lod_read_back_from_the_file(generated, zombie):
    """Each weapon has one mesh per colour LOD of the body, coarser each time (the body's LOD4 casts
    shadows only, its weapon from LOD3's), and the file keeps all of them."""
    body_lods = 1 + max(m.lod for m in zombie.meshes if m.piece != "body" or m.lod < 4)
    for name, prop in zombie.props.items():
        tris = [m.triangle_count for m in prop.lods]
        assert len(tris) == body_lods and all(a > b for a, b in zip(tris, tris[1:])), (name, tris)
        assert tris[-1] <= 32  # a far agent's weapon: fewer triangles than its hand has pixels
        for written, read in zip(generated.props[name].lods, prop.lods):
            np.testing.assert_array_equal(written.indices, read.indices)
            np.testing.assert_allclose(written.positions, read.positions, atol=1e-6)


def test_round_trip_keeps_skeleton_meshes_and_keys(generated, as_written):
    a, b = generated.skeleton, as_written.skeleton
    # The importer sorts parents-first by depth; map by name.
    order = [b.index(n) for n in a.names]
    np.testing.assert_array_equal([b.names[i] for i in order], a.names)
    np.testing.assert_allclose(b.rest_translation[order], a.rest_translation, atol=1e-6)
    np.testing.assert_allclose(b.inverse_bind[order], a.inverse_bind, atol=1e-6)
    for ma, mb in zip(generated.meshes, as_written.meshes):
        assert (ma.name, ma.piece, ma.lod, ma.group) == (mb.name, mb.piece, mb.lod, mb.group)
        np.testing.assert_array_equal(ma.positions, mb.positions)
        np.testing.assert_array_equal(ma.indices, mb.indices)
        np.testing.assert_allclose(ma.weights, mb.weights, atol=1e-6)
        mapped = np.array(order)[ma.joints.astype(np.int64)]
        np.testing.assert_array_equal(np.where(ma.weights > 0, mapped, 0), np.where(mb.weights > 0, mb.joints, 0))
    for ca, cb in zip(generated.clips, as_written.clips):
        assert (ca.name, ca.loop, ca.markers, ca.stride) == (cb.name, cb.loop, cb.markers, cb.stride)
        keys_b = {(b.names[ch.joint], ch.path): ch for ch in cb.channels}
        for ch in ca.channels:
            other = keys_b[(a.names[ch.joint], ch.path)]
            np.testing.assert_allclose(other.times, ch.times, atol=1e-6)
            np.testing.assert_allclose(other.values, ch.values, atol=1e-6)


def test_bind_pose_reproduces_the_mesh(zombie):
    skin = reference.skinning_matrices(zombie.skeleton, reference.rest_pose(zombie.skeleton))
    for m in zombie.meshes:
        np.testing.assert_allclose(reference.skin_points(skin, m.positions, m.joints, m.weights)[0], m.positions, atol=1e-5)


def test_structure_of_the_file():
    """What a viewer relies on: accessor bounds, POSITION min/max, index ranges, a default scene."""
    gl = pygltflib.GLTF2().load(str(ASSET_PATH))
    blob = gl.binary_blob()
    assert gl.scene == 0 and gl.scenes[0].nodes
    sizes = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
    ncomp = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
    for acc in gl.accessors:
        if acc.bufferView is None:  # a sparse morph target over zeros (or all zeros): its parts' views hold it
            parts = [] if acc.sparse is None else [(acc.sparse.indices.bufferView, sizes[acc.sparse.indices.componentType]),
                                                   (acc.sparse.values.bufferView, sizes[acc.componentType] * ncomp[acc.type])]
            assert acc.sparse is None or 1 <= acc.sparse.count <= acc.count
            for index, size in parts:
                view = gl.bufferViews[index]
                assert view.byteOffset % 4 == 0 and view.byteOffset + view.byteLength <= len(blob)
                assert acc.sparse.count * size <= view.byteLength
            continue
        view = gl.bufferViews[acc.bufferView]
        assert view.byteOffset % 4 == 0 and view.byteOffset + view.byteLength <= len(blob)
        assert (acc.byteOffset or 0) + acc.count * sizes[acc.componentType] * ncomp[acc.type] <= view.byteLength
    for mesh in gl.meshes:
        for prim in mesh.primitives:
            pos = gl.accessors[prim.attributes.POSITION]
            assert pos.min is not None and pos.max is not None
    for anim in gl.animations:
        for s in anim.samplers:
            assert gl.accessors[s.input].min is not None


@pytest.mark.parametrize("asset", ["zombie", "brute"])
def test_khronos_validator_finds_no_errors_or_warnings(asset):
    import importlib

    path = importlib.import_module(f"crowd.asset.{asset}").ASSET_PATH
    issues = khronos_issues(path)
    bad = [m for m in issues["messages"] if m["severity"] <= 1]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, bad[:5]
