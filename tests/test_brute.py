"""The built-in brute (crowd.asset.brute): the second zombie type a fresh clone mixes into its horde."""

from __future__ import annotations

import numpy as np
import pytest

from crowd.anim import reference
from crowd.anim.foot_skate import measure, to_world, joint_positions
from crowd.anim.roles import bake_roles, match_roles
from crowd.asset.brute import ASSET_PATH, build_character
from crowd.asset.gltf import load_character
from crowd.asset.gltf_write import glb_bytes
from crowd.asset.model import foot_joints
from crowd.anim import accuracy
from crowd.sim.locomotion import locomotion_layers
from crowd.sim.motion import motion_for


@pytest.fixture(scope="module")
def brute():
    return load_character("brute")


def test_committed_glb_is_what_the_generator_writes():
    assert ASSET_PATH.read_bytes() == glb_bytes(build_character()), "assets/brute.glb is stale: run python -m crowd.asset.brute"


def _bind_joints(character) -> dict:
    bind = np.linalg.inv(character.skeleton.inverse_bind)
    return {n: bind[i, :3, 3] for i, n in enumerate(character.skeleton.names)}


def test_the_same_rig_in_a_heavier_build(brute, zombie):
    """The zombie's joints and names (so roles, masks, feet and the socket are found alike), taller, with
    broader shoulders and a wider stance; its meshes bulkier than the zombie's across every axis."""
    assert sorted(brute.skeleton.names) == sorted(zombie.skeleton.names) and brute.sockets.keys() == zombie.sockets.keys()
    b, z = _bind_joints(brute), _bind_joints(zombie)
    assert b["head"][1] > 1.05 * z["head"][1]
    assert b["upper_arm_l"][0] - b["upper_arm_r"][0] > 1.3 * (z["upper_arm_l"][0] - z["upper_arm_r"][0])
    assert b["foot_l"][0] - b["foot_r"][0] > 1.2 * (z["foot_l"][0] - z["foot_r"][0])
    body = lambda c: next(m for m in c.meshes if m.piece == "body" and m.lod == 0).positions
    assert np.all(np.ptp(body(brute), axis=0) > 1.08 * np.ptp(body(zombie), axis=0))
    assert {m.piece for m in brute.meshes} == {m.piece for m in zombie.meshes}  # the same variation pieces


def test_its_walk_and_charge_plant_their_feet_and_are_slower_than_the_zombies(brute, zombie):
    """The float64 reference's feet, walked at each clip's own speed as the AI animates it: under 1 cm of
    slide per metre (the zombie's bar), and a slower, heavier gait than the zombie's."""
    motions = {}
    for name, character in (("brute", brute), ("zombie", zombie)):
        roles, _ = match_roles(character.clips)
        baked = bake_roles(character, roles)
        motions[name] = m = motion_for(character, baked, roles)
        if name == "zombie":
            continue
        feet = foot_joints(character.skeleton)
        for speed in (m.walk_speed, m.run_speed):
            rate, frames = 120.0, 400
            layers, walked = locomotion_layers(m, speed, frames, 1.0 / rate)
            truth = accuracy.truth(character.skeleton, [character.clip(c.name) for c in baked.clips], layers)
            world = to_world(joint_positions(truth, character.skeleton, feet), np.stack([np.zeros(frames), walked], axis=1), 0.0)
            skate = measure(world, 1.0 / rate, float(walked[-1]), [character.skeleton.names[j] for j in feet])
            assert skate.worst_cm_per_m < 1.0, (speed, skate)
    assert motions["brute"].walk_speed < 0.95 * motions["zombie"].walk_speed
    assert motions["brute"].run_speed < 0.8 * motions["zombie"].run_speed


def test_its_smash_is_two_handed(brute):
    """Both hands meet on the handle at the strike: the left hand within a forearm's length of the right."""
    sk = brute.skeleton
    clip = brute.clip("attack")
    g = reference.global_matrices(sk, reference.sample_clip(sk, clip, np.array([clip.markers["impact"]])))[0]
    gap = np.linalg.norm(g[sk.index("hand_l"), :3, 3] - g[sk.index("hand_r"), :3, 3])
    assert gap < 0.3, gap
    wind_up = reference.global_matrices(sk, reference.sample_clip(sk, clip, np.array([0.38])))[0]
    assert wind_up[sk.index("hand_r"), 1, 3] > wind_up[sk.index("head"), 1, 3]  # raised above the head first


def test_it_stands_on_the_ground_and_ends_lying_down(brute):
    sk = brute.skeleton
    g = reference.global_matrices(sk, reference.sample_clip(sk, brute.clip("idle"), np.linspace(0, 1, 9)))
    for side in "lr":
        assert np.all(np.abs(g[:, sk.index(f"foot_{side}"), 1, 3] - 0.0945) < 0.02)
    g = reference.global_matrices(sk, reference.sample_clip(sk, brute.clip("death"), np.array([1.0])))
    assert g[0, sk.index("head"), 1, 3] < 0.45
