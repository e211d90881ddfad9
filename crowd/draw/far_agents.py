"""Agents drawn only as impostors get their key from the processor and nothing else: no joint is blended,
composed or written for them, their morph pairs are left out and their foot lock is freed
(shaders/processor.comp.glsl, ``key_alone``). The crowd on the GPU and the compute processor only: the
processor reads where each agent stands from the GPU crowd's own buffer.

The cull picks the impostor from the distance of an agent's bound centre, so an agent whose ground point is
farther than ``beyond_m`` (the impostor distance, its fade band, the bound's offset from the ground point,
and a margin) is drawn as its impostor alone, in the view and in every shadow cascade.

The margin is what keeps the palette of frame F - N whole where it is drawn. A body is drawn with the
palette of the frame its weapons were read back from (crowd.draw.sync), up to RING frames old. An agent
drawn as a mesh now was within ``beyond_m`` in each of those frames as long as neither it nor the camera
moved more than a step a frame (CAMERA_STEP_M, AGENT_STEP_M), the margin being RING such steps. A frame
that breaks that (a camera cut, a long frame, the impostor distance raised) is a cut: the kept palettes
are dropped (PaletteSync.reset) and every body is drawn with this frame's until they are whole again,
the weapons hidden meanwhile, as after a new crowd.
"""

from __future__ import annotations

import math

import numpy as np

from .readback import RING

CAMERA_STEP_M = 1.0  # metres the camera may move in a frame without a cut (60 m/s at 60 frames a second)
AGENT_STEP_M = 1.0  # metres an agent may move in a frame without a cut
MARGIN_M = RING * (CAMERA_STEP_M + AGENT_STEP_M)


class FarAgents:
    """The distance past which agents get their key alone, and whether this frame is a cut."""

    def __init__(self):
        self._eye: np.ndarray | None = None
        self._beyond = math.inf

    def beyond(self, impostor_m: float, fade_m: float, bound_offset_m: float) -> float:
        """Metres from the camera past which an agent's ground point is surely drawn as its impostor alone,
        with the margin the palette history needs."""
        return float(impostor_m) + float(fade_m) + float(bound_offset_m) + MARGIN_M

    def cut(self, eye, beyond_m: float, agent_step_m: float) -> bool:
        """Whether this frame breaks the margin's assumptions (see the module): the camera or an agent moved
        more than a step, or the distance grew. Remembers this frame's camera and distance."""
        eye = np.asarray(eye, np.float64)
        cut = self._eye is None or float(np.linalg.norm(eye - self._eye)) > CAMERA_STEP_M or agent_step_m > AGENT_STEP_M \
            or beyond_m > self._beyond
        self._eye, self._beyond = eye.copy(), float(beyond_m)
        return cut
