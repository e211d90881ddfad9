"""The view a frame is drawn from: the camera-relative view-projection, its planes, and what
``CrowdRenderer.prepare`` hands every later pass of the frame (``FrameView``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pyglm import glm

from ..frame import Camera
from .shadows import Cascades


def view_proj(camera: Camera) -> np.ndarray:
    """Camera-relative view-projection (the eye at the origin): float32 4x4, rows as in the maths
    (numpy's view of a pyglm matrix); upload it with ``gl_bytes``."""
    forward = np.asarray(camera.target, np.float64) - np.asarray(camera.eye, np.float64)
    view = glm.lookAt(glm.vec3(0.0), glm.vec3(*forward.astype(np.float32)), glm.vec3(0.0, 1.0, 0.0))
    proj = glm.perspective(math.radians(camera.fov_y), camera.aspect, camera.near, camera.far)
    return np.array(proj * view, dtype=np.float32).reshape(4, 4)


@dataclass(frozen=True)
class FrameView:
    """What ``CrowdRenderer.prepare`` decided for one frame, handed to every pass after it."""

    camera: Camera
    view_proj: np.ndarray  # float32 4x4, camera-relative
    shadow: Cascades | None  # the sun's shadow cascades (their light matrices); None without shadows
    visible: np.ndarray | None  # bool (N,): agents that survived culling (None on the GPU cull path)
    casting: np.ndarray | None = None  # bool (cascades, N): agents in each cascade's volume, whose shadows it draws (CPU path, shadows on)
    lod: np.ndarray | None = None  # int (N,): each agent's colour LOD (CPU path; its weapon's LOD follows it)
    held: np.ndarray | None = None  # bool (N,): drawn as its impostor alone, which holds its weapon (CPU path)


def frustum_planes(view_proj: np.ndarray) -> np.ndarray:
    """(6, 4) normalised planes (inside: dot(n, p) + d >= 0) of a view-projection (rows as in the maths)."""
    m = np.asarray(view_proj, np.float64)
    planes = np.stack([m[3] + m[0], m[3] - m[0], m[3] + m[1], m[3] - m[1], m[3] + m[2], m[3] - m[2]])
    return planes / np.linalg.norm(planes[:, :3], axis=1, keepdims=True)


def gl_bytes(matrix: np.ndarray) -> bytes:
    """A 4x4 matrix (rows as in the maths) in the column-major order GLSL's mat4 expects."""
    return np.ascontiguousarray(np.asarray(matrix, np.float32).T).tobytes()
