"""Other builds of the rig (crowd.asset.brute, crowd.asset.survivor): the zombie's meshes moved onto a
Body whose joints stand elsewhere, each vertex carried and scaled by the bones it is skinned to."""

from __future__ import annotations

import numpy as np

from .mesh_builder import _quantise
from .model import SkinnedMesh, vertex_normals
from .morph_targets import with_targets
from .rig import JOINT_NAMES, ZOMBIE_BODY, Body

# The bone each joint's vertices scale about: its own (to the child named here), else (a leaf: the
# head, the jaw, the left hand, the socket, the toes) its parent's.
_CHILD = {"hips": "spine", "spine": "chest", "chest": "neck", "neck": "head", "hand_r": "hand_r_socket",
          **{f"{a}_{s}": f"{b}_{s}" for s in "lr" for a, b in (("shoulder", "upper_arm"), ("upper_arm", "forearm"), ("forearm", "hand"),
                                                              ("thigh", "shin"), ("shin", "foot"), ("foot", "toe"))}}


def _scale_about_bones(body: Body, girth: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per joint: the zombie's rest position, `body`'s, and the 3x3 scale about the joint's bone: along
    the bone by its change in length, across it by the joint's `girth` (x, y, z: the components across
    the bone, in model axes at rest; by joint name, or its name without the side)."""
    names = JOINT_NAMES
    before, after = ZOMBIE_BODY.positions(), body.positions()
    parents = [names.index(p) if p else -1 for _, p, _ in ZOMBIE_BODY.joints]
    scales = np.zeros((len(names), 3, 3))
    for j, name in enumerate(names):
        base = name[:-2] if name.endswith(("_l", "_r")) else name
        if name in _CHILD:
            c = names.index(_CHILD[name])
            bone_before, bone_after = before[c] - before[j], after[c] - after[j]
        else:  # a leaf: its parent's bone
            p = parents[j]
            bone_before, bone_after = before[j] - before[p], after[j] - after[p]
        d = bone_before / np.linalg.norm(bone_before)
        along = np.linalg.norm(bone_after) / np.linalg.norm(bone_before)
        across = np.eye(3) - np.outer(d, d)
        scales[j] = along * np.outer(d, d) + across @ np.diag(girth.get(name, girth[base])) @ across
    return before, after, scales


def remodel(mesh: SkinnedMesh, body: Body, girth: dict, name: str, targets: bool = True) -> SkinnedMesh:
    """A zombie mesh on `body`'s skeleton: each vertex moved by its joints' moves (position, and scale
    about the bone), blended by its own skin weights, as skinning blends; normals made anew; quantised
    as the zombie's are; its morph targets carried over (or left out: `targets` False). Named after
    `name` instead of the zombie."""
    before, after, scales = _scale_about_bones(body, girth)
    p = np.asarray(mesh.positions, np.float64)
    moved = np.zeros_like(p)
    for k in range(mesh.joints.shape[1]):
        j = mesh.joints[:, k].astype(np.int64)
        w = mesh.weights[:, k].astype(np.float64)[:, None]
        moved += w * (after[j] + np.einsum("vij,vj->vi", scales[j], p - before[j]))
    total = np.sum(mesh.weights, axis=1, dtype=np.float64)[:, None]
    moved = _quantise(moved / total, 1e-6)
    normals = _quantise(vertex_normals(moved, mesh.indices.astype(np.int64)), 1e-6)
    out = SkinnedMesh(name=mesh.name.replace("zombie_", f"{name}_"), piece=mesh.piece, lod=mesh.lod, positions=moved.astype(np.float32),
                      normals=normals.astype(np.float32), joints=mesh.joints, weights=mesh.weights, indices=mesh.indices, colors=mesh.colors,
                      base_color=mesh.base_color, group=mesh.group)
    if not targets or not mesh.morph_count:
        return out
    # A target's deltas move as its vertex's neighbourhood does: by the linear part of the same blend.
    deltas = np.zeros(mesh.morph_positions.shape)
    for k in range(mesh.joints.shape[1]):
        j = mesh.joints[:, k].astype(np.int64)
        w = mesh.weights[:, k].astype(np.float64)[:, None]
        deltas += w * np.einsum("vij,tvj->tvi", scales[j], np.asarray(mesh.morph_positions, np.float64))
    return with_targets(out, deltas / total)
