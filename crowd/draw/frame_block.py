"""The frame's constants in one uniform block (shaders/frame.glsl): the camera's view-projection, the
sun, sky and fog, and the shadow cascades. The renderer writes it once a frame, where the values
changed, into one buffer bound to one binding point; each program that reads it is pointed at that
binding once, when it is made (``use_frame_block``). The colour, ground, splat, town and weapon passes
then set none of these per program."""

from __future__ import annotations

import moderngl
import numpy as np

from ..gl import GLObjects, GLStage
from ..lighting import LIGHTING
from .shadows import CASCADES
from .view import FrameView

FRAME_BINDING = 1  # the uniform-block binding point it is bound to (the GPU AI's Kinds block is on 0)
FRAME_DEFINES = {"CASCADES": CASCADES}  # every shader that includes frame.glsl: one layout for all

# std140: a mat4 is 64 bytes, a vec4 16; arrays of them are tightly packed.
_FLOATS = 16 + 16 * CASCADES + 4 * CASCADES + 4 * 5


def use_frame_block(prog) -> None:
    """Point `prog`'s Frame block (where it reads it) at FRAME_BINDING."""
    block = prog.get("Frame", None)
    if block is not None:
        block.binding = FRAME_BINDING


def frame_constants(view: FrameView, fog_density: float) -> np.ndarray:
    """The block's float32 data for `view` (its camera, and its cascades where the scene has shadows)."""
    out = np.zeros(_FLOATS, np.float32)
    out[:16] = np.asarray(view.view_proj, np.float32).T.ravel()  # column-major, as GLSL's mat4
    at = 16
    if view.shadow is not None:
        for k, matrix in enumerate(view.shadow.view_proj):
            out[at + 16 * k: at + 16 * (k + 1)] = np.asarray(matrix, np.float32).T.ravel()
        cascade = out[at + 16 * CASCADES: at + 20 * CASCADES].reshape(CASCADES, 4)
        cascade[:, 0], cascade[:, 1] = view.shadow.texel_m, view.shadow.depth_bias
    at += 20 * CASCADES
    out[at:] = np.concatenate(list(lighting_vectors(fog_density).values()))
    return out


def lighting_vectors(fog_density: float) -> dict[str, tuple]:
    """The block's lighting members by name (frame.glsl), each four floats: the sun, sky and ground
    colours and directions of crowd.lighting, and the fog's colour with `fog_density` per metre."""
    out = {name: (*LIGHTING[name], 0.0) for name in ("u_sun_dir", "u_sun_color", "u_sky_color", "u_ground_color")}
    out["u_fog"] = (*LIGHTING["u_fog_color"], float(fog_density))
    return out


class FrameBlock(GLStage):
    def __init__(self, ctx: moderngl.Context):
        self._objects = GLObjects()
        self.buffer = self._objects.add(ctx.buffer(reserve=_FLOATS * 4))
        self._written: bytes | None = None

    def write(self, view: FrameView, fog_density: float) -> None:
        """This frame's constants, written where they changed, and the block bound."""
        data = frame_constants(view, fog_density).tobytes()
        if data != self._written:
            self.buffer.write(data)
            self._written = data
        self.buffer.bind_to_uniform_block(FRAME_BINDING)

    def gpu_bytes(self) -> int:
        return self.buffer.size

    def release(self) -> None:
        self._objects.release()
