"""The built-in zombie's clips retargeted to a humanoid whose file has none (issue 44, point 3): the joint
map for the common naming schemes, rest poses aligned, the legs' ratio, the feet on the ground during the
walk's stance; a character that is not a humanoid is refused in one line naming what it lacks."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from conftest import shared
from crowd.asset.gltf import load_character
from crowd.asset.gltf.reader import GltfImportError
from crowd.asset.gltf_write import write_glb
from crowd.asset.model import Skeleton
from crowd.asset.pose import global_matrices, rest_pose, sample_clip
from crowd.asset.retarget import RetargetError, joint_map, retarget_clips
from gltf_factory import clipless_gltf

PHASES = np.linspace(0.0, 1.0, 121)
MIXAMO = {"hips": "Hips", "spine": "Spine", "chest": "Spine2", "neck": "Neck", "head": "Head", "jaw": "Jaw"}
PACK = {"hips": "Hips", "spine": "Abdomen", "chest": "Torso", "neck": "Neck", "head": "Head", "jaw": "Jaw"}
for _side, _word, _dot in (("l", "Left", "L"), ("r", "Right", "R")):
    MIXAMO.update({f"shoulder_{_side}": f"{_word}Shoulder", f"upper_arm_{_side}": f"{_word}Arm", f"forearm_{_side}": f"{_word}ForeArm",
                   f"hand_{_side}": f"{_word}Hand", f"thigh_{_side}": f"{_word}UpLeg", f"shin_{_side}": f"{_word}Leg",
                   f"foot_{_side}": f"{_word}Foot", f"toe_{_side}": f"{_word}ToeBase"})
    PACK.update({f"shoulder_{_side}": f"Shoulder.{_dot}", f"upper_arm_{_side}": f"UpperArm.{_dot}", f"forearm_{_side}": f"LowerArm.{_dot}",
                 f"hand_{_side}": f"Wrist.{_dot}", f"thigh_{_side}": f"UpperLeg.{_dot}", f"shin_{_side}": f"LowerLeg.{_dot}",
                 f"foot_{_side}": f"Foot.{_dot}", f"toe_{_side}": f"Toe.{_dot}"})


@pytest.fixture(scope="module")
def zombie():
    return load_character(None)


def _renamed(skeleton, names: dict, prefix: str = ""):
    return dataclasses.replace(skeleton, names=tuple(prefix + names.get(n, n) for n in skeleton.names))


def _stance_error(target, clips, zombie, ratio: float) -> float:
    """The largest distance of either ankle, while the zombie's is on the ground (within 1 cm of its
    lowest), from where the zombie's is, scaled from the ground up: metres."""
    tmap, smap = joint_map(target)[0], joint_map(zombie.skeleton)[0]
    walk = next(c for c in clips if c.name == "shamble")
    tw = global_matrices(target, sample_clip(target, walk, PHASES))
    zw = global_matrices(zombie.skeleton, sample_clip(zombie.skeleton, zombie.clip("shamble"), PHASES))
    t0, z0 = global_matrices(target, rest_pose(target))[0], global_matrices(zombie.skeleton, rest_pose(zombie.skeleton))[0]
    worst = 0.0
    for side in "lr":
        tf_, zf = tmap[f"foot.{side}"], smap[f"foot.{side}"]
        zy = zw[:, zf, 1, 3]
        planted = zy <= zy.min() + 0.01
        expect = t0[tf_, 1, 3] + (zy - z0[zf, 1, 3]) * ratio
        worst = max(worst, float(np.abs(tw[:, tf_, 1, 3] - expect)[planted].max()))
    return worst


def test_a_mixamo_named_rig_of_the_zombies_shape_gets_the_zombies_poses_back(zombie, tmp_path):
    plain = load_character(None, merge=False)
    path = tmp_path / "mixamo.glb"
    write_glb(dataclasses.replace(plain, skeleton=_renamed(plain.skeleton, MIXAMO, "mixamorig:"), clips=[], sockets={}), path)
    c = load_character(path)
    assert [clip.name for clip in c.clips] == [clip.name for clip in zombie.clips]
    assert any("retargeted to it (joint map: Mixamo names, 21 roles mapped; legs 1 times the zombie's)" in w for w in c.warnings)
    tmap, smap = joint_map(c.skeleton)[0], joint_map(zombie.skeleton)[0]
    for clip in zombie.clips:
        got = global_matrices(c.skeleton, sample_clip(c.skeleton, c.clip(clip.name), PHASES))
        want = global_matrices(zombie.skeleton, sample_clip(zombie.skeleton, clip, PHASES))
        for role, j in tmap.items():
            assert np.abs(got[:, j, :3, 3] - want[:, smap[role], :3, 3]).max() < 1e-6, (clip.name, role)


@pytest.mark.parametrize("thigh, shin", [(0.9, 1.1), (0.8, 1.3)])
def test_a_packs_rig_of_other_proportions_keeps_its_feet_on_the_ground(zombie, thigh, shin):
    sk = _renamed(zombie.skeleton, PACK)
    rest = np.asarray(sk.rest_translation, np.float64).copy()
    names = list(sk.names)
    for side in "LR":  # other thighs and shins, shorter forearms, an A-pose's arms lowered 40 degrees
        rest[names.index(f"LowerLeg.{side}")] *= thigh
        rest[names.index(f"Foot.{side}")] *= shin
        rest[names.index(f"LowerArm.{side}")] *= 0.85
    from crowd import transforms as tf

    rotation = np.asarray(sk.rest_rotation, np.float64).copy()
    for side, sign in (("L", -1.0), ("R", 1.0)):
        j = names.index(f"UpperArm.{side}")
        rotation[j] = tf.quat_mul(tf.quat_from_axis_angle([0.0, 0.0, 1.0], sign * np.radians(40.0)), rotation[j])
    target = dataclasses.replace(sk, rest_translation=rest, rest_rotation=rotation)
    # Bound in that pose, as a rig of those proportions is (its meshes modelled on it).
    target = dataclasses.replace(target, inverse_bind=np.linalg.inv(global_matrices(target, rest_pose(target))[0]))
    clips, line = retarget_clips(target, zombie.skeleton, zombie.clips, "pack")
    assert "the free packs' (UpperLeg.L) names" in line
    ratio = float(line.split("legs ")[1].split(" times")[0])
    assert ratio == pytest.approx((thigh + shin) / 2.0, abs=0.01)
    assert all(c.stride is None for c in clips)  # (measured from the clip's own planted feet, as for any clip)
    assert _stance_error(target, clips, zombie, ratio) <= 0.002  # (the two-bone IK puts each ankle where it belongs)
    # Rest poses aligned: the A-posed upper arm points where the zombie's does in each pose.
    tmap, smap = joint_map(target)[0], joint_map(zombie.skeleton)[0]
    tw = global_matrices(target, sample_clip(target, clips[0], PHASES))
    zw = global_matrices(zombie.skeleton, sample_clip(zombie.skeleton, zombie.clips[0], PHASES))
    for side in "lr":
        a = tw[:, tmap[f"lower_arm.{side}"], :3, 3] - tw[:, tmap[f"upper_arm.{side}"], :3, 3]
        b = zw[:, smap[f"lower_arm.{side}"], :3, 3] - zw[:, smap[f"upper_arm.{side}"], :3, 3]
        cos = np.sum(a * b, axis=1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
        assert np.degrees(np.arccos(np.clip(cos.min(), -1.0, 1.0))) < 0.01


def test_a_rig_that_is_not_a_humanoid_is_refused_naming_what_it_lacks(tmp_path, zombie):
    with pytest.raises(GltfImportError, match="no clips, and the built-in clips cannot be retargeted to it: no joint found for hips, chest, head") as info:
        load_character(clipless_gltf(tmp_path))
    assert "\n" not in str(info.value) and "body.gltf" in str(info.value)
    two = Skeleton(("a", "b"), np.array([-1, 0]), np.zeros((2, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (2, 1)), np.ones((2, 3)),
                   np.tile(np.eye(4), (2, 1, 1)))
    with pytest.raises(RetargetError, match="two joints: no clips"):
        retarget_clips(two, zombie.skeleton, zombie.clips, "two joints")


def test_a_real_pack_character_without_its_clips_walks_with_its_feet_on_the_ground(tmp_path, zombie):
    source = shared("Quaternius_Characters_Matt_SingleWeapon.gltf")
    doc = json.loads(Path(source).read_text())
    doc.pop("animations")
    for item in [*doc["buffers"], *doc.get("images", [])]:  # (its files stay where they are)
        if "uri" in item and not item["uri"].startswith("data:"):
            (tmp_path / item["uri"]).write_bytes((Path(source).parent / item["uri"]).read_bytes())
    path = tmp_path / "matt.gltf"
    path.write_text(json.dumps(doc))
    c = load_character(path)
    line = next(w for w in c.warnings if "retargeted" in w)
    ratio = float(line.split("legs ")[1].split(" times")[0])
    assert _stance_error(c.skeleton, c.clips, zombie, ratio) <= 0.002
