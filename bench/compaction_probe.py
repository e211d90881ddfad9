"""`crowd-bench compaction`: the GPU cull's list compaction two ways, on the same agents and camera.

- atomics (the runtime's, shaders/cull.comp.glsl): one dispatch; each work group counts its agents
  per draw in shared memory and reserves its range of each list with one global atomic per draw;
- prefix sum (shaders/bench/cull_prefix.comp.glsl): three dispatches; the work groups' counts are
  scanned per draw, so no global atomics at all and each group's range is known before it writes.

Both cull with cull_common.glsl's code, so their lists hold the same agents; ``run`` checks that per
draw before it times them. The crowd is the demo's (the default scene's AI and camera), every agent's
record uploaded once; each variant is timed with timer queries over `repeats` back-to-back runs after
10 to bring the clocks up.
"""

from __future__ import annotations

import math

import moderngl
import numpy as np

from crowd.draw.gpu_cull import BUFFER_UPDATE, COMMAND, GROUP_SIZE, SHADER_STORAGE, VERTEX_ATTRIB_ARRAY
from crowd.draw.render import INSTANCE_DTYPE, frustum_planes, view_proj
from crowd.gl import load_shader


def _lists(renderer) -> list[set]:
    """The agents in each draw's colour list."""
    cull = renderer.gpu
    counts = np.frombuffer(cull.commands.read(size=cull.draw_count * 20), np.uint32).reshape(-1, 5)[:, 1]
    records = np.frombuffer(cull.lists.read(), INSTANCE_DTYPE)
    out = []
    for d, c in enumerate(counts):
        first, _ = cull.list_of(d)
        texel = records["packed"][first: first + int(c), 0]
        out.append(set(renderer.palette.agents_at(texel & 0xFFF, texel >> 12).tolist()))
    return out


class PrefixCompaction:
    """The three-dispatch variant over a renderer's GPU cull (its buffers, and the uniforms its last
    colour dispatch set)."""

    def __init__(self, ctx: moderngl.Context, renderer):
        self.ctx, self.renderer, self.cull = ctx, renderer, renderer.gpu
        self.program = ctx.compute_shader(load_shader("bench/cull_prefix.comp.glsl"))
        self.groups = math.ceil(self.cull.agents / GROUP_SIZE)
        self.counts = ctx.buffer(reserve=max(self.groups * self.cull.draw_count, 1) * 4)

    def run(self) -> None:
        cull, p = self.cull, self.program
        for name in p:
            if name in cull.program and isinstance(p[name], moderngl.Uniform):
                p[name].write(cull.program[name].read())
        p["u_write_visible"] = 0
        p["u_occlusion"] = 0
        p["u_list_base"] = 0
        p["u_record_base"] = 0
        p["u_work_groups"] = self.groups
        cull.agents_buffer.bind_to_storage_buffer(0)
        cull.lists.bind_to_storage_buffer(1)
        cull.commands.bind_to_storage_buffer(2)
        cull.draw_of.bind_to_storage_buffer(3)
        cull.list_start.bind_to_storage_buffer(6)
        self.counts.bind_to_storage_buffer(5)
        for phase, groups in ((0, self.groups), (1, cull.draw_count), (2, self.groups)):
            p["u_phase"] = phase
            p.run(group_x=groups)
            self.ctx.memory_barrier(SHADER_STORAGE)
        self.ctx.memory_barrier(VERTEX_ATTRIB_ARRAY | COMMAND | BUFFER_UPDATE)

    def release(self) -> None:
        self.counts.release()
        self.program.release()


def measure(ctx: moderngl.Context, pipeline, repeats: int = 40) -> dict:
    """Both variants on the agents of the pipeline's AI and its camera (a pipeline without weapons: no
    visibility buffer): the lists compared per draw, then each timed."""
    renderer = pipeline.renderer
    cull = renderer.gpu
    renderer.prepare(pipeline.camera, pipeline.instances(), 0, cull_now=False, palette=pipeline.processor.layout)  # every record uploaded
    planes = frustum_planes(view_proj(pipeline.camera))
    empty = np.frombuffer(cull.commands.read(), np.uint32).copy()  # the commands as uploaded: counts 0

    def atomics():
        cull._dispatch(cull.lists, cull.commands, None, planes, 0.0, renderer.lod_distances, renderer.culling, 0, None, 1)

    prefix = PrefixCompaction(ctx, renderer)
    query = ctx.query(time=True)
    try:
        listed = {}
        for name, run in (("atomics", atomics), ("prefix_sum", prefix.run)):
            cull.commands.write(empty.tobytes())
            run()
            ctx.finish()
            listed[name] = _lists(renderer)
        times = {}
        for name, run in (("atomics", atomics), ("prefix_sum", prefix.run)):
            samples = []
            for k in range(10 + repeats):
                cull.commands.write(empty.tobytes())
                with query:
                    run()
                if k >= 10:
                    samples.append(query.elapsed / 1e6)
            times[name] = round(float(np.median(samples)), 4)
        return {"agents": cull.agents, "draws": cull.draw_count, "same_lists": listed["atomics"] == listed["prefix_sum"],
                "listed": int(sum(len(s) for s in listed["atomics"])), "ms": times}
    finally:
        prefix.release()
