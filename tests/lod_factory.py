"""Characters made in code for the generated-LOD tests (tests/test_generated_lods.py): a tube skinned
along a chain of joints that bends in its one clip, with the extremes a real file can bring (a UV seam,
flat shading, no index buffer, morph targets, hundreds of joints, thousands of vertices)."""

from __future__ import annotations

import numpy as np

from crowd.asset.model import Channel, Character, Clip, SkinnedMesh, Skeleton, Texture
from crowd.transforms import quat_from_axis_angle


def tube_character(joints: int = 8, rings: int = 24, segments: int = 16, seam: bool = True, flat: bool = False,
                   indexed: bool = True, morphs: int = 0, height: float = 1.8, radius: float = 0.15, name: str = "tube") -> Character:
    """A tube `height` tall around the y axis, `rings` rings of `segments` vertices, skinned to a chain of
    `joints` joints (each vertex to the two joints around its height), with a clip that bends every
    joint. `seam`: texture coordinates around it, the first column repeated at u = 1 (a UV seam);
    `flat`: every quad its own four vertices with the quad's normal (hard edges everywhere); `indexed`
    False: every triangle its own three vertices; `morphs`: targets that bulge rings of it."""
    columns = segments + 1 if seam else segments
    angle = 2.0 * np.pi * (np.arange(columns) % segments) / segments
    y = np.linspace(0.0, height, rings)
    # A waist, so that the silhouette has curves to lose.
    r = radius * (1.0 + 0.3 * np.sin(np.linspace(0.0, 3.0 * np.pi, rings)))
    pos = np.stack([np.outer(r, np.cos(angle)), np.repeat(y[:, None], columns, 1), np.outer(r, np.sin(angle))], axis=-1).reshape(-1, 3)
    normal = np.stack([np.cos(angle), np.zeros(columns), np.sin(angle)], axis=-1)
    normals = np.broadcast_to(normal, (rings, columns, 3)).reshape(-1, 3)
    uvs = np.stack(np.meshgrid(np.arange(columns) / segments, y / height), axis=-1).reshape(-1, 2)
    quads = []
    for i in range(rings - 1):
        for s in range(segments):
            a, b = i * columns + s, i * columns + (s + 1) % columns
            quads.append((a, b, a + columns, b + columns))
    quads = np.array(quads)
    # Skin: each ring to the two joints around its height.
    along = y / height * (joints - 1)
    low = np.minimum(np.floor(along).astype(int), joints - 2) if joints > 1 else np.zeros(rings, int)
    frac = along - low if joints > 1 else np.zeros(rings)
    ring_joints = np.zeros((rings, 4), np.uint16)
    ring_weights = np.zeros((rings, 4), np.float32)
    ring_joints[:, 0], ring_weights[:, 0] = low, 1.0 - frac
    if joints > 1:
        ring_joints[:, 1], ring_weights[:, 1] = low + 1, frac
    ring_weights /= ring_weights.sum(axis=1, keepdims=True)
    vertex_ring = np.repeat(np.arange(rings), columns)
    deltas = np.zeros((morphs, len(pos), 3))
    for t in range(morphs):
        bulge = np.exp(-((vertex_ring - (t + 1) * rings / (morphs + 1)) / 2.0) ** 2)
        deltas[t] = 0.05 * bulge[:, None] * np.stack([np.cos(angle[np.arange(len(pos)) % columns]), np.zeros(len(pos)),
                                                       np.sin(angle[np.arange(len(pos)) % columns])], axis=-1)
    if flat:
        # Every quad its own corners, each with the quad's normal.
        corners = quads.reshape(-1)
        face = np.cross(pos[quads[:, 2]] - pos[quads[:, 0]], pos[quads[:, 1]] - pos[quads[:, 0]])
        face /= np.linalg.norm(face, axis=1, keepdims=True)
        take = corners
        normals = np.repeat(face, 4, axis=0)
        pos, uvs, vertex_ring, deltas = pos[take], uvs[take], vertex_ring[take], deltas[:, take]
        quads = np.arange(4 * len(quads)).reshape(-1, 4)
    # Triangles wound outwards: (a, c, b) and (b, c, d).
    indices = np.concatenate([quads[:, [0, 2, 1]], quads[:, [1, 2, 3]]], axis=1).reshape(-1)
    if not indexed:
        pos, normals, uvs, vertex_ring, deltas = pos[indices], normals[indices], uvs[indices], vertex_ring[indices], deltas[:, indices]
        indices = np.arange(len(indices))
    mesh = SkinnedMesh(name=f"{name}_body", piece="body", lod=0, positions=pos.astype(np.float32), normals=np.asarray(normals, np.float32),
                       joints=ring_joints[vertex_ring], weights=ring_weights[vertex_ring], indices=indices.astype(np.uint32),
                       texture=0 if seam else -1, uvs=uvs.astype(np.float32) if seam else None)
    if morphs:
        mesh.morph_targets = np.arange(morphs)
        mesh.morph_positions = deltas.astype(np.float32)
        mesh.morph_normals = np.zeros_like(mesh.morph_positions)
    step = height / max(joints - 1, 1)
    skeleton = Skeleton(
        names=tuple(f"joint{j}" for j in range(joints)), parents=np.arange(-1, joints - 1, dtype=np.int32),
        rest_translation=np.array([[0.0, 0.0 if j == 0 else step, 0.0] for j in range(joints)]),
        rest_rotation=np.tile([0.0, 0.0, 0.0, 1.0], (joints, 1)), rest_scale=np.ones((joints, 3)),
        inverse_bind=np.stack([np.linalg.inv(_translation(0.0, j * step, 0.0)) for j in range(joints)]))
    bend = np.radians(60.0) / max(joints - 1, 1)  # the whole chain bends 60 degrees at the clip's middle
    keys = np.stack([quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), a) for a in (0.0, bend, 0.0)])
    clip = Clip("bend", [Channel(j, "rotation", "LINEAR", np.array([0.0, 0.5, 1.0]), keys.copy()) for j in range(1, joints)], 0.0, 1.0, True)
    texture = [Texture("checker", np.full((4, 4, 4), 200, np.uint8))] if seam else []
    return Character(name, skeleton, [mesh], [clip], textures=texture, morphs=tuple(f"bulge{t}" for t in range(morphs)),
                     morph_defaults=np.zeros(morphs)).validate()


def _translation(x: float, y: float, z: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m
