"""Rigid meshes on joints drawn as the body is: each becomes a skinned piece whose every vertex is
weighted 1 to its joint, so it is drawn, culled, shadowed and LOD'd by the same instanced path as the
body, with no draw path of its own.

A rigid mesh follows its joint as ``world = joint_world @ offset @ p``. A skinned vertex is drawn at
``joint_world @ inverse_bind @ p_bind``, so the piece's bind-space positions are
``bind @ offset @ p`` (bind = inverse(inverse_bind)), and its normals turn by the inverse transpose of
that matrix's linear part. The character has one copy of the piece per LOD level (the same triangles:
these are small), so it does not vanish at distance. Props (the weapons the crowd holds in a socket)
are not attachments and stay props.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .model import Attachment, Character, SkinnedMesh


def attachment_piece(character: Character, attachment: Attachment, lod: int, piece: str) -> SkinnedMesh:
    bind = np.linalg.inv(np.asarray(character.skeleton.inverse_bind[attachment.joint], np.float64))
    to_bind = bind @ np.asarray(attachment.offset, np.float64)
    mesh = attachment.mesh
    points = np.c_[np.asarray(mesh.positions, np.float64), np.ones(len(mesh.positions))] @ to_bind.T
    turn = np.linalg.inv(to_bind[:3, :3]).T  # normals: the inverse transpose (offsets may scale)
    normals = np.asarray(mesh.normals, np.float64) @ turn.T
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    count = len(points)
    joints = np.zeros((count, 4), np.uint16)
    joints[:, 0] = attachment.joint
    weights = np.zeros((count, 4), np.float32)
    weights[:, 0] = 1.0
    return SkinnedMesh(name=mesh.name, piece=piece, lod=lod, positions=points[:, :3].astype(np.float32),
                       normals=normals.astype(np.float32), joints=joints, weights=weights,
                       indices=np.asarray(mesh.indices, np.uint32), colors=mesh.colors, base_color=mesh.base_color,
                       texture=mesh.texture, uvs=mesh.uvs, unlit=mesh.unlit)


def attachments_as_pieces(character: Character) -> Character:
    """`character` with every attachment turned into skinned pieces (one per LOD level), and none left."""
    if not character.attachments:
        return character
    lods = sorted({m.lod for m in character.meshes}) or [0]
    taken = {m.piece for m in character.meshes}
    pieces = []
    for i, attachment in enumerate(character.attachments):
        piece = f"rigid{i}:{attachment.mesh.name}"
        while piece in taken:
            piece += "'"
        taken.add(piece)
        pieces += [attachment_piece(character, attachment, lod, piece) for lod in lods]
    return dataclasses.replace(character, meshes=[*character.meshes, *pieces], attachments=[], warnings=list(character.warnings))
