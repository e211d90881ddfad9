"""The view a frame is drawn from: the camera-relative view-projection, its planes, the sun's cascades
kept while nothing they are made from moves (``CascadeCache``), and what ``CrowdRenderer.prepare`` hands
every later pass of the frame (``FrameView``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pyglm import glm

from ..frame import Camera
from .shadows import Cascades, cascades


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


class CascadeCache:
    """The sun's cascades (crowd.draw.shadows) and their frustum planes, made again only when the camera,
    sun, crowd box, tile or fog changed: a still camera's frames share them (their float64 numpy is
    small arrays, a third of a millisecond a frame in Python)."""

    def __init__(self):
        self._made = (None, None)  # (what the cascades were made from, them)
        self._planes = (None, None)  # (the cascades, their planes)

    def cascades(self, camera: Camera, sun_dir, box: tuple[np.ndarray, np.ndarray], tile: int, fog: float) -> Cascades:
        key = (np.asarray(camera.eye, np.float64).tobytes(), np.asarray(camera.target, np.float64).tobytes(), camera.fov_y, camera.near,
               camera.far, camera.aspect, np.asarray(sun_dir, np.float64).tobytes(), np.asarray(box[0], np.float64).tobytes(),
               np.asarray(box[1], np.float64).tobytes(), int(tile), float(fog))
        if key != self._made[0]:
            self._made = (key, cascades(camera, sun_dir, box, tile, fog))
        return self._made[1]

    def planes(self, shadow: Cascades) -> np.ndarray:
        """(cascades, 6, 4) frustum planes of `shadow`'s light matrices."""
        if self._planes[0] is not shadow:
            self._planes = (shadow, np.stack([frustum_planes(m) for m in shadow.view_proj]))
        return self._planes[1]


def focal_px(height_px: float, fov_y: float) -> float:
    """Pixels a metre spans at a metre's depth in a view `height_px` rows tall with a vertical field of
    view of `fov_y` degrees: an object's height on screen is its height times this over its depth."""
    return 0.5 * float(height_px) / math.tan(math.radians(fov_y) / 2.0)


def gl_bytes(matrix: np.ndarray) -> bytes:
    """A 4x4 matrix (rows as in the maths) in the column-major order GLSL's mat4 expects."""
    return np.ascontiguousarray(np.asarray(matrix, np.float32).T).tobytes()
