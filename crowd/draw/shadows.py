"""The sun's shadow cascades: where each shadow map tile looks, in float64.

Contract: ``cascades(camera, sun_dir, crowd_box, tile)`` → ``Cascades`` with, per cascade k, the
camera-relative light view-projection (float32 (C, 4, 4), the matrix the shadow pass draws tile k with
and the lighting samples it through), the world size of one of its texels, and the depth bias that
size needs. Two cascades:

- cascade 0, near: the box of up to 60 m around the camera's target that the single shadow map of
  earlier versions covered (a texel of 6 cm at most with 2,048 texels), so the zombies near the
  camera look as they did;
- cascade 1, the visible crowd: the part of the crowd's box (the AI's world square, as tall as an
  agent) inside the view frustum, cut at the frustum's far plane, at the crowd's farthest corner or
  where the fog leaves a tenth of a shadow's contrast (576 m), whichever is nearest: far zombies get
  a shadow at their feet, which a 60 m map left out entirely.

A fragment takes the first cascade whose tile holds it (shaders/lighting.glsl). Each box is as deep
as the crowd's box seen from the sun, so every agent that can shadow a point in it is drawn into it;
its size moves in steps of 5 % and its centre in whole texels of the world along the sun's axes, so
a moving camera does not make the shadows' edges crawl. The two tiles sit side by side in one depth texture, and each cascade culls
its own shadow lists (crowd.draw.gpu_cull, CrowdRenderer.prepare).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..frame import Camera

CASCADES = 2
NEAR_REACH = (12.0, 60.0)  # metres: cascade 0's half width, 1.2 times the distance to the target within these
SIZE_STEP = 1.05
FOG_CONTRAST = 0.1  # the far cascade ends where fog leaves this share of a shadow's contrast


@dataclass(frozen=True)
class Cascades:
    view_proj: np.ndarray  # float32 (C, 4, 4), camera-relative
    texel_m: np.ndarray  # float32 (C,): the world size of one texel of each tile
    depth_bias: np.ndarray  # float32 (C,): in each tile's depth units (0..1), two texels' worth of slope
    reach_m: np.ndarray  # float32 (C,): agents whose sphere starts farther than this from the eye cast nothing into the cascade


def _cross(a, b) -> np.ndarray:
    """The cross product of two 3-vectors: numpy's general one costs 40 µs a call in axis handling,
    and the cascades are recomputed every frame."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _look(sun: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) whose rows are the light's right, up and backward (toward the sun) axes."""
    back = sun / np.linalg.norm(sun)
    right = _cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    return np.stack([right, _cross(back, right), back])


def _ortho(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """GL orthographic projection of the light-space box [lo, hi] (z toward the sun: -z is forward)."""
    m = np.eye(4)
    m[0, 0], m[1, 1] = 2.0 / (hi[0] - lo[0]), 2.0 / (hi[1] - lo[1])
    m[2, 2] = -2.0 / (hi[2] - lo[2])  # near at z = hi[2] (closest to the sun), far at lo[2]
    m[0, 3] = -(hi[0] + lo[0]) / (hi[0] - lo[0])
    m[1, 3] = -(hi[1] + lo[1]) / (hi[1] - lo[1])
    m[2, 3] = (hi[2] + lo[2]) / (hi[2] - lo[2])
    return m


def _frustum_corners(camera: Camera, far: float) -> np.ndarray:
    """(8, 3) camera-relative corners of the view frustum from its near plane to `far`."""
    eye, target = np.asarray(camera.eye, np.float64), np.asarray(camera.target, np.float64)
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = _cross(forward, [0.0, 1.0, 0.0])  # the view matrix's up (render.view_proj)
    right /= np.linalg.norm(right)
    up = _cross(right, forward)
    tan_y = np.tan(np.radians(camera.fov_y) / 2.0)
    out = []
    for d in (camera.near, far):
        h, w = d * tan_y, d * tan_y * camera.aspect
        for sx in (-1.0, 1.0):
            for sy in (-1.0, 1.0):
                out.append(forward * d + right * (sx * w) + up * (sy * h))
    return np.asarray(out)


def cascades(camera: Camera, sun_dir, crowd_box: tuple[np.ndarray, np.ndarray], tile: int, fog_density: float = 0.0) -> Cascades:
    """The light matrices of both cascades for this camera; `crowd_box` is the world box (lo, hi)
    float64 every agent stands in, `tile` the texels of a tile's side; with `fog_density` (per metre,
    shaders/lighting.glsl's exponential fog) the far cascade ends where fog leaves a tenth of a
    shadow's contrast (576 m at the default 0.004), so agents past it cast nothing."""
    eye = np.asarray(camera.eye, np.float64)
    rotation = _look(np.asarray(sun_dir, np.float64))
    lo, hi = (np.asarray(v, np.float64) - eye for v in crowd_box)
    box = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    box_light = box @ rotation.T  # the crowd's box in light space (camera-relative)
    target = np.asarray(camera.target, np.float64) - eye
    reach = float(np.clip(np.linalg.norm(target) * 1.2, *NEAR_REACH))
    target_light = rotation @ target
    boxes = [(target_light[:2] - reach, target_light[:2] + reach)]
    fogged = np.log(1.0 / FOG_CONTRAST) / fog_density if fog_density > 0 else np.inf
    far = float(min(camera.far, np.max(np.linalg.norm(box, axis=1)), fogged))
    # A caster's shadow ends at most its height times the sun's run over rise from it: one farther than
    # that beyond the far cascade's end shadows nothing the cascade covers. The light-space box alone
    # kept 96 % of the demo camera's 100,000 agents as casters, the sun being low.
    sun = np.asarray(sun_dir, np.float64) / np.linalg.norm(sun_dir)
    shadow_run = float(hi[1] - lo[1]) * np.sqrt(max(1.0 - sun[1] ** 2, 0.0)) / max(sun[1], 0.05)
    caster_reach = np.array([np.inf, far + shadow_run], np.float32)
    corners = _frustum_corners(camera, max(far, camera.near * 2.0)) @ rotation.T
    seen_lo = np.maximum(corners[:, :2].min(axis=0), box_light[:, :2].min(axis=0))
    seen_hi = np.minimum(corners[:, :2].max(axis=0), box_light[:, :2].max(axis=0))
    if np.any(seen_hi <= seen_lo):  # no part of the crowd in view: cover the frustum
        seen_lo, seen_hi = corners[:, :2].min(axis=0), corners[:, :2].max(axis=0)
    boxes.append((seen_lo, seen_hi))
    # Depth: every caster in the crowd's box, plus cascade 0's own reach where the box is shallow.
    z_lo = min(box_light[:, 2].min(), target_light[2] - reach) - 1.0
    z_hi = max(box_light[:, 2].max(), target_light[2] + reach) + 1.0
    eye_light = (rotation @ eye)[:2]  # snapping happens in world-anchored light space
    matrices, texels, biases = [], [], []
    for xy_lo, xy_hi in boxes:
        # Square texels with a margin for the PCF kernel; the size in steps of 5 % and the centre on
        # whole texels of the world, so a moving camera neither resizes nor slides the texel grid
        # continuously (either would make the shadows' edges crawl).
        size = SIZE_STEP ** np.ceil(np.log(float(np.max(xy_hi - xy_lo)) * 1.02 + 1e-3) / np.log(SIZE_STEP))
        texel = size / tile
        center = np.floor(((xy_lo + xy_hi) / 2.0 + eye_light) / texel) * texel - eye_light
        b_lo = np.array([center[0] - size / 2, center[1] - size / 2, z_lo])
        b_hi = np.array([center[0] + size / 2, center[1] + size / 2, z_hi])
        view = np.eye(4)
        view[:3, :3] = rotation
        matrices.append(_ortho(b_lo, b_hi) @ view)
        texels.append(texel)
        biases.append(2.0 * texel / (z_hi - z_lo))
    return Cascades(np.asarray(matrices, np.float32), np.asarray(texels, np.float32), np.asarray(biases, np.float32), caster_reach)
