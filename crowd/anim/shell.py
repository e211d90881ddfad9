"""ACL's error measure (the Animation Compression Library): virtual vertices on a shell around each joint.

A vertex skinned rigidly to a joint at ``SHELL_M`` = 3 cm from it, along each of the joint's bind-pose
axes, both ways. Rotation errors show as 3 cm times the angle, translation errors in full, and both add
up through the hierarchy, because the matrices compared are the skinning matrices a vertex shader uses.
Below every other module of the stage: the bake's compressor (crowd.anim.compress) meets its error
bound in this measure, and crowd.anim.accuracy reports the pipeline's error in it.
"""

from __future__ import annotations

import numpy as np

from ..asset.model import Skeleton

SHELL_M = 0.03


def shell_points(skeleton: Skeleton, radius: float = SHELL_M) -> np.ndarray:
    """(J, 6, 4) homogeneous bind-space points: each joint's position ± radius along its bind axes."""
    bind = np.linalg.inv(skeleton.inverse_bind)  # (J, 4, 4) joint → model space at bind time
    axes = bind[:, :3, :3] / np.linalg.norm(bind[:, :3, :3], axis=1, keepdims=True)  # unit columns
    offsets = np.concatenate([axes, -axes], axis=2).transpose(0, 2, 1) * radius  # (J, 6, 3)
    points = np.ones((skeleton.joint_count, 6, 4))
    points[..., :3] = bind[:, None, :3, 3] + offsets
    return points


def shell_error(palette: np.ndarray, truth_matrices: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P, J, 6) metres between the shell points skinned by `palette` ((P, J, 3, 4) rows, any float)
    and by the float64 truth ((P, J, 3|4, 4))."""
    delta = np.asarray(palette, np.float64)[..., :3, :] - np.asarray(truth_matrices, np.float64)[..., :3, :]
    return np.linalg.norm(np.einsum("pjrc,jkc->pjkr", delta, points), axis=-1)
