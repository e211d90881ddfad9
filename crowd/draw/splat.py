"""The smallest impostors drawn by compute passes instead of quads (shaders/impostor_splat.comp.glsl).

On the H200 the graphics pipeline runs on a small part of the chip, and an instanced quad costs it about
the same whether it covers one pixel or thirty: at a million agents on the benchmark's overview camera
the median impostor is one pixel tall, and the colour pass's 875,000 quads were most of the frame even
with every one of them collapsed in its vertex shader (docs/BENCHMARKS.md has the figures). So where the
crowd is culled on the GPU (the lists and commands of crowd.draw.gpu_cull), the splat first sorts each
impostor draw's colour list: an impostor shorter than ``splat_px`` whose quad spans at most MAX_SIDE
pixels either way goes to the splat's own list, the rest back into the draw's list, whose command then
draws only those. One compute invocation per splatted impostor visits the pixels of its quad's screen
rectangle and casts each centre onto the quad's plane: the sample, depth and lighting are those the
quad's fragment would get, so the picture is the quads' up to rounding (tests/test_splat.py measures it).

The pixels are independent of the order invocations run in: each pixel's nearest depth (atomicMin over
its bits), then the lowest agent record at that depth, then that record alone writes its colour. A
full-screen pass (impostor_resolve.frag.glsl) then writes those pixels with their depth, so meshes,
quads, town and ground sort against them by the depth test. The quads' list comes back in the order the
sort's atomics gave, as the cull's lists do (crowd.draw.gpu_cull): the depth test makes the picture the
same in any order.

Its buffers: three 4-byte words a pixel of the viewport, and two per agent record and impostor draw for
the sorted lists, made only where a colour pass draws impostors with the splat on (``gpu_bytes``'s "splat").
"""

from __future__ import annotations

import math

import moderngl
import numpy as np

from ..gl import GLObjects, GLStage, load_shader, set_uniforms
from .draw_programs import fixed_units
from .view import focal_px, gl_bytes

SPLAT_PX = 8.0  # impostors shorter than this many pixels are splatted (docs/BENCHMARKS.md: the measured choice)
# An impostor whose bound spans fewer pixels than this holds no weapon in the view (shaders/cull.comp.glsl):
# the weapon is under a pixel there, and a graphics instance each (docs/BENCHMARKS.md: its cost and error).
HELD_PX = 4.0
MAX_SIDE = 16  # pixels: a quad whose screen rectangle spans more either way (lying, or seen wide) stays a quad
GROUP = 64  # impostor_splat.comp.glsl's local size
MAX_GROUPS_X = 32768  # work groups a dispatch row (within GL's guaranteed 65,535)
CLEAR, SORT, REQUEUE, WINNER, COLOUR = range(5)  # its passes
# What reads the passes' writes: the shaders (storage), the quads' draws (their commands and entries).
_BARRIER = 0x2000 | 0x40 | 0x1  # GL_SHADER_STORAGE_BARRIER_BIT | GL_COMMAND_BARRIER_BIT | GL_VERTEX_ATTRIB_ARRAY_BARRIER_BIT


def _run_over(prog, invocations: int) -> None:
    """Dispatch `prog` over at least `invocations` (GROUP a work group), in rows of at most MAX_GROUPS_X
    groups: GL promises 65,535 groups a dimension, and a 4K viewport's pixels need 129,600."""
    groups = math.ceil(invocations / GROUP)
    across = min(groups, MAX_GROUPS_X)
    prog.run(across, math.ceil(groups / across), 1)


class ImpostorSplat(GLStage):
    """The splat's programs and buffers for one renderer; ``run`` before the quads, ``resolve`` after."""

    def __init__(self, ctx: moderngl.Context, defines: dict, unlit: list[bool]):
        """`defines`: the colour pass's lighting defines (shadows and cascades), as its impostor program has;
        `unlit`: per impostor draw (one per character with an atlas), whether its character is unlit. Each
        draw has a program of its own, so that its atlas's constants are written once."""
        self.ctx = ctx
        self._objects = GLObjects()
        self._buffers = GLObjects()
        self.programs = [self._objects.add(fixed_units(ctx.compute_shader(load_shader(
            "impostor_splat.comp.glsl", {**defines, "NO_INSTANCE_ENTRY": 1, **({"UNLIT": 1} if flat else {})})))) for flat in unlit or [False]]
        self.resolve_program = self._objects.add(ctx.program(vertex_shader=load_shader("impostor_resolve.vert.glsl"),
                                                             fragment_shader=load_shader("impostor_resolve.frag.glsl")))
        self._triangle = self._objects.add(ctx.vertex_array(self.resolve_program, []))
        self._size = (0, 0)
        self._records = self._draws = 0
        self.pixels = self.sorted = self.counts = None
        self._unresolved = False  # a run whose pixels are not yet in a frame

    def _ensure(self, size: tuple[int, int], records: int, draws: int) -> None:
        """Buffers for a viewport of `size` pixels, `records` agent records and `draws` impostor draws (made
        again only to grow past them, or for another viewport)."""
        size = tuple(int(x) for x in size)
        if size == self._size and records <= self._records and draws <= self._draws:
            return
        self._buffers.release()
        grow = size == self._size
        self._size, self._records, self._draws = size, max(records, self._records if grow else 0, 1), max(draws, self._draws if grow else 0, 1)
        count = size[0] * size[1]
        self.pixels = tuple(self._buffers.add(self.ctx.buffer(reserve=4 * count)) for _ in range(3))
        self.sorted = self._buffers.add(self.ctx.buffer(reserve=4 * 2 * self._records * self._draws))
        self.counts = self._buffers.add(self.ctx.buffer(reserve=4 * 2 * self._draws))

    def run(self, framebuffer, view, renderer, processor, draws, records: int, splat_px: float) -> None:
        """Splat the small impostors of `draws` ((command index, character) of each impostor draw, drawn
        from renderer.gpu's lists, their keys in `processor`'s palette) into this viewport's pixels, and
        leave the rest in the draws' lists; `records`: agent records in the crowd (a list holds each at
        most once: an agent's fade copies go to two draws)."""
        size = tuple(framebuffer.viewport[2:])
        if min(size) <= 0:  # (a minimised window: no pixel to splat into, and the quads draw nothing there either)
            return
        self._ensure(size, records, len(draws))
        focal = focal_px(size[1], view.camera.fov_y)
        constants = {"u_inverse_view_proj": gl_bytes(np.linalg.inv(np.asarray(view.view_proj, np.float64))),
                     "u_size": size, "u_focal_px": float(focal), "u_splat_px": float(splat_px), "u_max_side": MAX_SIDE, "u_draws": len(draws),
                     "u_region": self._records}
        for k, (command, character) in enumerate(draws):
            prog = self.programs[k]
            set_uniforms(prog, **constants, u_command=int(command), u_draw=k)
            processor.bind_palette(0, prog)
        renderer.bind_shadow_map()  # (the camera and the light: the frame block)
        renderer.gpu.entries.bind_to_storage_buffer(0)
        renderer.gpu.commands.bind_to_storage_buffer(1)
        for binding, buffer in enumerate((*self.pixels, self.sorted, self.counts), start=2):
            buffer.bind_to_storage_buffer(binding)
        for step in (CLEAR, SORT, REQUEUE, WINNER, COLOUR):
            if step != CLEAR:
                self.ctx.memory_barrier(_BARRIER)
            for k, (command, character) in enumerate(draws):
                prog = self.programs[k]
                if step != REQUEUE:  # (which reads no texture; every sampler is on its unit before the first dispatch)
                    renderer.bind_impostor(character, prog)
                set_uniforms(prog, u_pass=step)
                if step == CLEAR:
                    _run_over(prog, max(size[0] * size[1], 2 * len(draws)))
                    break
                _run_over(prog, max(records, 1))
        self.ctx.memory_barrier(_BARRIER)
        self._unresolved = True

    def resolve(self, framebuffer) -> None:
        """The last run's pixels into `framebuffer`, depth-tested (nothing where no run is pending: a colour
        pass drawn without the splat draws every impostor as a quad)."""
        if not self._unresolved:
            return
        self._unresolved = False
        framebuffer.use()
        for binding, buffer in enumerate(self.pixels, start=2):
            buffer.bind_to_storage_buffer(binding)
        set_uniforms(self.resolve_program, u_size=self._size)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self._triangle.render(moderngl.TRIANGLES, vertices=3)

    def gpu_bytes(self) -> int:
        return self._buffers.gpu_bytes()

    def release(self) -> None:
        self._buffers.release()
        self._objects.release()
        self.pixels = self.sorted = self.counts = None
