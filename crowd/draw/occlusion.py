"""Occlusion culling's depth pyramid (Hi-Z), for the GPU cull path (GL 4.3).

Contract:
- ``capture(framebuffer, view_proj, eye)``, after a frame's colour passes: its depth is copied into a
  texture of this stage's own (a blit, so the window's framebuffer works as an offscreen one does)
  and reduced into a pyramid of R32F levels, each texel the farthest depth of the 2 x 2 (at odd
  edges 3) texels below it, one compute dispatch a level (shaders/hiz.comp.glsl). The camera it was
  drawn from (its view-projection and float64 eye) is kept with it.
- ``bind(program, eye)`` before the next frame's cull: shaders/cull.comp.glsl projects each agent's
  bounding box through the kept camera (agents are camera-relative: the eye's move since is added in
  float64, then rounded) and drops the agent where the box's nearest depth lies behind the farthest
  depth of the 2 x 2 pyramid texels its screen rectangle covers, at the level where it covers at most
  2 x 2.

What it costs in correctness: the pyramid is the previous frame's, so an agent that comes out from
behind an occluder, or into a view the camera jumped to, is drawn one frame late. Nothing that was
visible in the previous frame and stays so is dropped: an agent's own body lies inside its box, so
it cannot hide it. The colour pass alone is culled this way; shadows come from the sun's side.

It exists only with occlusion culling on (``gpu_bytes`` shows it): the pyramid and its depth copy
take 1.33 x 4 bytes a pixel at half resolution, plus a depth copy and a spare colour buffer of 4
bytes a pixel each (19.4 MB at 1920x1080).
"""

from __future__ import annotations

import math

import moderngl
import numpy as np

from ..gl import GLObjects, GLStage, load_shader, set_uniforms

SHADER_IMAGE_ACCESS, TEXTURE_FETCH = 0x20, 0x8
HIZ_UNIT = 7  # the texture unit the cull samples the pyramid on (the palette takes 0-2, the albedo 6)


class DepthPyramid(GLStage):
    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self._objects = GLObjects()
        self._sized = GLObjects()  # what depends on the frame's size
        self.program = self._objects.add(ctx.compute_shader(load_shader("hiz.comp.glsl")))
        self.size: tuple[int, int] | None = None
        self.colours = 0
        self.depth = self.fbo = self.pyramid = None
        self.levels: list[tuple[int, int]] = []
        self.view_proj: np.ndarray | None = None  # the camera the pyramid holds, None before the first capture
        self.eye: np.ndarray | None = None
        self.unusable: str | None = None  # why the frame's depth could not be copied (then nothing is culled)

    def _allocate(self, size: tuple[int, int], colours: int) -> None:
        self._sized.release()
        self.size, self.colours = size, colours
        self.depth = self._sized.add(self.ctx.depth_texture(size))
        self.depth.compare_func = ""  # plain depth values for texelFetch
        # moderngl blits colour and depth together, between framebuffers with as many colour
        # attachments: these receive the colour copy nobody reads (8 MB at 1080p, a GPU-side copy).
        spare = [self._sized.add(self.ctx.renderbuffer(size, 4)) for _ in range(colours)]
        self.fbo = self._sized.add(self.ctx.framebuffer(color_attachments=spare, depth_attachment=self.depth))
        w, h = max(1, (size[0] + 1) // 2), max(1, (size[1] + 1) // 2)
        self.levels = [(w, h)]
        while self.levels[-1] != (1, 1):
            pw, ph = self.levels[-1]
            self.levels.append((max(1, pw // 2), max(1, ph // 2)))
        self.pyramid = self._sized.add(self.ctx.texture((w, h), 1, dtype="f4"))
        self.pyramid.build_mipmaps(0, len(self.levels) - 1)  # allocates the levels (GL halves them as self.levels does)
        self.pyramid.extra = {"mipmapped": True}  # gpu_bytes counts the levels
        self.pyramid.filter = (moderngl.NEAREST_MIPMAP_NEAREST, moderngl.NEAREST)
        self.view_proj = None

    def capture(self, framebuffer: moderngl.Framebuffer, view_proj: np.ndarray, eye) -> None:
        size = tuple(framebuffer.size)
        colours = len(framebuffer.color_attachments or ()) or 1  # the window's framebuffer lists none: it has one
        if (size, colours) != (self.size, self.colours):
            self._allocate(size, colours)
        if self.unusable is not None:
            return
        self.ctx.error  # clear an earlier error, so the check below sees the blit's
        self.ctx.copy_framebuffer(self.fbo, framebuffer)
        error = self.ctx.error
        if error != "GL_NO_ERROR":
            # A framebuffer whose depth format differs from the copy's cannot be blitted: testing
            # against what the copy holds would hide visible agents, so occlusion culling stops.
            self.unusable = f"occlusion culling is off: this framebuffer's depth could not be copied ({error})"
            self.view_proj = None
            return
        p = self.program
        finer = size
        for level, (w, h) in enumerate(self.levels):
            p["u_from_depth"] = int(level == 0)
            p["u_finer_size"] = finer
            p["u_size"] = (w, h)
            if level == 0:
                self.depth.use(0)
            else:
                self.pyramid.bind_to_image(0, read=True, write=False, level=level - 1)
            self.pyramid.bind_to_image(1, read=False, write=True, level=level)
            p.run(math.ceil(w / 8), math.ceil(h / 8))
            self.ctx.memory_barrier(SHADER_IMAGE_ACCESS | TEXTURE_FETCH)
            finer = (w, h)
        self.view_proj = np.asarray(view_proj, np.float32)
        self.eye = np.asarray(eye, np.float64).copy()

    def bind(self, program, eye) -> bool:
        """Point the cull's occlusion uniforms at the pyramid; False (no test this frame) before the first capture."""
        if self.view_proj is None or self.unusable is not None:
            set_uniforms(program, u_occlusion=0)
            return False
        self.pyramid.use(HIZ_UNIT)
        set_uniforms(program, u_hiz=HIZ_UNIT, u_occlusion=1, u_hiz_view_proj=np.ascontiguousarray(self.view_proj.T).tobytes(),
                     u_hiz_eye_delta=tuple(float(v) for v in (np.asarray(eye, np.float64) - self.eye)), u_hiz_size=tuple(self.levels[0]),
                     u_hiz_levels=len(self.levels))
        return True

    def gpu_bytes(self) -> int:
        return self._objects.gpu_bytes() + self._sized.gpu_bytes()

    def release(self) -> None:
        self._sized.release()
        self._objects.release()
        self.depth = self.fbo = self.pyramid = None
