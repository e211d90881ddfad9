"""The built-in zombie, generated entirely by code: ``python -m crowd.asset.zombie`` writes assets/zombie.glb.

Why generate it rather than ship an artist's file: the project must run with nothing downloaded, and
every vertex, weight and key here is reproducible from code a reader can change. The output is
byte-for-byte deterministic (all floats are quantised before they are packed), so a test can
regenerate the file and compare it with the committed one.

Conventions: metres, +Y up, the character faces +Z, its left side is +X. The rest pose is a T-pose
with every joint's local rotation at identity, so joint axes are world-aligned at rest.

Weapon socket ("weapon_r", joint ``hand_r_socket``): origin at the centre of the closed right fist,
8 cm past the wrist; +Y runs along the held handle towards the weapon's head (out of the thumb side
of the fist), +Z points out of the palm, +X points back towards the wrist. Weapons are modelled with
the handle along +Y; each has a ``*_grip`` node whose frame is placed onto the socket frame.

This module assembles the character; its parts are made by crowd.asset.rig (the skeleton),
crowd.asset.zombie_meshes (with crowd.asset.mesh_builder, palette and morph_targets), crowd.asset.zombie_weapons
and crowd.asset.zombie_clips (keyed by crowd.asset.clip_keys, posed by pose_angles and planted_feet).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..resources import ASSET_DIR
from .clip_keys import build_clips
from .model import Character
from .morph_targets import MORPH_TARGETS
from .rig import SOCKET_JOINT, build_skeleton
from .zombie_meshes import build_meshes
from .zombie_weapons import build_props

# The generator's names stay importable from here, where callers have always found them.

ASSET_PATH = ASSET_DIR / "zombie.glb"


def build_character() -> Character:
    skeleton = build_skeleton()
    return Character(
        name="zombie",
        skeleton=skeleton,
        meshes=build_meshes(),
        clips=build_clips(skeleton),
        props=build_props(),
        sockets={"weapon_r": skeleton.index(SOCKET_JOINT)},
        morphs=MORPH_TARGETS,
        morph_defaults=np.zeros(len(MORPH_TARGETS)),
    ).validate()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="Generate the built-in zombie and write it as a binary glTF.")
    parser.add_argument("--out", type=Path, default=ASSET_PATH, help=f"output .glb (default {ASSET_PATH})")
    args = parser.parse_args(argv)
    from .gltf_write import write_glb

    character = build_character()
    size = write_glb(character, args.out)
    lod_tris = {}
    for m in character.meshes:
        lod_tris.setdefault(m.lod, {})[m.piece] = m.triangle_count
    print(f"wrote {args.out} ({size} bytes): {character.skeleton.joint_count} joints, "
          f"{len(character.clips)} clips, triangles per LOD {json.dumps(lod_tris)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
