"""The built-ins' morph targets: displacement fields in bind space, and with_targets, which adds them (and
the change of the normals they make) to a mesh."""

from __future__ import annotations

import dataclasses

import numpy as np

from .mesh_builder import _quantise, _smoothstep
from .model import SkinnedMesh, vertex_normals

# Morph targets (issue 23): each a displacement field in bind space, applied to every piece and LOD
# alike (the shadow proxy too), so a piece's LODs share its shapes by construction. The clips key
# "snarl" (crowd.asset.zombie_clips.SNARL); the others are a body variation a scene gives each zombie
# (crowd.anim.morph).

MORPH_TARGETS = ("snarl", "belly_swell", "chest_sunken", "gaunt")


def _morph_displacements(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(T, V, 3) displacements of bind positions `p` with normals `n` at weight 1."""
    out = np.zeros((len(MORPH_TARGETS), len(p), 3))
    x, y, z = p[:, 0], p[:, 1], p[:, 2]

    def blob(centre, radii):
        d = (p - np.asarray(centre)) / np.asarray(radii)
        return _smoothstep(1.0 - np.sqrt(np.sum(d * d, axis=1)))

    # Snarl: the upper lip and nose pulled up and back, the lower lip down, the cheeks up.
    upper = blob((0.0, 1.68, 0.10), (0.055, 0.03, 0.06))
    lower = blob((0.0, 1.645, 0.10), (0.045, 0.02, 0.06))
    cheeks = blob((0.045, 1.675, 0.085), (0.03, 0.03, 0.05)) + blob((-0.045, 1.675, 0.085), (0.03, 0.03, 0.05))
    out[0] = upper[:, None] * [0.0, 0.012, -0.006] + lower[:, None] * [0.0, -0.010, 0.002] + cheeks[:, None] * [0.0, 0.008, -0.004]
    # The torso's own region: the arms (out past the shoulders in the T-pose) and the legs below the hips stay.
    torso = _smoothstep((0.24 - np.abs(x)) / 0.06) * _smoothstep((y - 0.80) / 0.1)
    radial = np.stack([x, np.zeros_like(x), z + 0.01], axis=1)
    radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9)
    front = np.maximum(radial[:, 2], 0.0)
    # Swollen belly: out around the navel, most to the front.
    out[1] = radial * (0.07 * np.exp(-(((y - 1.05) / 0.1) ** 2)) * (0.3 + 0.7 * front) * torso)[:, None]
    # Sunken chest: the breastbone in.
    out[2] = -radial * (0.035 * np.exp(-(((y - 1.33) / 0.07) ** 2)) * front ** 2 * torso)[:, None]
    # Gaunt: the torso, neck and face 1.2 cm in along their normals (the limbs are thin already).
    out[3] = -n * (0.012 * _smoothstep((0.26 - np.abs(x)) / 0.05) * _smoothstep((y - 0.85) / 0.1))[:, None]
    return out


def with_targets(mesh: SkinnedMesh, displacements: np.ndarray | None = None) -> SkinnedMesh:
    """`mesh` with the zombie's morph targets: position deltas as given (default its own bind
    displacements), normal deltas the change of its smooth normals; quantised as positions are."""
    p = np.asarray(mesh.positions, np.float64)
    idx = mesh.indices.astype(np.int64)
    d = _morph_displacements(p, np.asarray(mesh.normals, np.float64)) if displacements is None else displacements
    d = _quantise(d, 1e-6)
    base = vertex_normals(p, idx)
    normals = np.stack([_quantise(vertex_normals(p + dk, idx) - base, 1e-6) for dk in d])
    return dataclasses.replace(mesh, morph_targets=np.arange(len(MORPH_TARGETS)), morph_positions=d.astype(np.float32),
                               morph_normals=normals.astype(np.float32))
