"""Flat rings on the ground: the player (red) and the selected zombie (yellow). Only the window draws
them, so only the window makes their program and buffers."""

from __future__ import annotations

import math

import moderngl
import numpy as np

from crowd.draw.view import FrameView, gl_bytes
from crowd.gl import GLObjects, GLStage, load_shader

SEGMENTS = 48


class MarkerRings(GLStage):
    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self._objects = GLObjects()
        self.program = self._objects.add(ctx.program(vertex_shader=load_shader("marker.vert.glsl"), fragment_shader=load_shader("marker.frag.glsl")))
        a = np.linspace(0.0, 2.0 * math.pi, SEGMENTS + 1)
        strip = np.stack([np.repeat(a, 2), np.tile([0.0, 1.0], SEGMENTS + 1)], axis=1).astype(np.float32)
        ring = self._objects.add(ctx.buffer(strip.tobytes()))
        self._instances = self._objects.add(ctx.buffer(reserve=32))
        self._vao = self._objects.add(ctx.vertex_array(self.program, [(ring, "2f", "in_ring"),
                                                              (self._instances, "4f 4f/i", "i_position_radius", "i_color")]))
        self._vertices = len(strip)

    def draw(self, framebuffer, view: FrameView, points, radii, colors) -> None:
        """Rings at world points (M, 3), float64, with radii (M,) and linear RGBA colours (M, 4)."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        if not len(points):
            return
        data = np.zeros((len(points), 8), np.float32)
        data[:, :3] = points - np.asarray(view.camera.eye, np.float64)[None]
        data[:, 3] = np.broadcast_to(np.asarray(radii, np.float64), (len(points),))
        data[:, 4:] = np.broadcast_to(np.asarray(colors, np.float64).reshape(-1, 4), (len(points), 4))
        if self._instances.size != data.nbytes:
            self._instances.orphan(data.nbytes)
        self._instances.write(data.tobytes())
        framebuffer.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.program["u_view_proj"].write(gl_bytes(view.view_proj))
        self._vao.render(moderngl.TRIANGLE_STRIP, vertices=self._vertices, instances=len(points))

    def gpu_bytes(self) -> int:
        return self._objects.gpu_bytes()

    def release(self) -> None:
        self._objects.release()
