"""crowd-bench fragment: the GL 3.3 / 4.1 fragment processor against the compute one (issue 25, point 1).

For each agent count, the same random layers (4 a agent) through both processors of the built-in zombie,
GPU time by timer queries (the median of `repeats` runs): the compute dispatch; the fragment path's whole
run, its locals pass alone and its compose pass alone; and the floor of any fragment pass over the same
texels, a shader writing constants into the same three RGBA32F targets (and into one). Where the compose
pass runs at that floor, what bounds the path is the writing of the palette, not the animation.
"""

from __future__ import annotations

import contextlib

import numpy as np

from .common import random_layers


def measure(ctx, counts: list[int], repeats: int = 20) -> list[dict]:
    import moderngl

    from crowd.anim.processor import LOCALS_UNITS, AnimationProcessor
    from crowd.anim.roles import bake_roles, match_roles
    from crowd.asset.gltf import load_character
    from crowd.gl import GLObjects, has_compute, load_shader

    character = load_character(None)
    roles, _ = match_roles(character.clips)
    baked = bake_roles(character, roles)
    rows = []
    with contextlib.ExitStack() as stack:
        objects = GLObjects()
        stack.callback(objects.release)
        query = ctx.query(time=True)  # (a moderngl query has no release: the context frees it)
        floors = {k: objects.add(ctx.program(vertex_shader=load_shader("processor.vert.glsl"), geometry_shader=load_shader("processor.geom.glsl"),
                                             fragment_shader=load_shader("bench/fill_floor.frag.glsl", {"TARGETS": k}))) for k in (3, 1)}

        def gpu_ms(fn) -> float:
            samples = []
            for _ in range(repeats + 2):  # (the first runs compile and upload)
                with query:
                    fn()
                samples.append(query.elapsed / 1e6)
            return float(np.median(samples[2:]))

        for n in counts:
            layers = random_layers(n, 4, len(baked.clips), np.random.default_rng(1))
            row = {"agents": n}
            if has_compute(ctx):
                with AnimationProcessor(ctx, baked, 4, path="compute") as proc:
                    proc.resize(n)
                    proc.upload(layers)
                    row["compute_ms"] = gpu_ms(proc.run)
            with AnimationProcessor(ctx, baked, 4, path="fragment") as proc, contextlib.ExitStack() as inner:
                scratch = GLObjects()
                inner.callback(scratch.release)
                proc.resize(n)
                proc.upload(layers)
                row["fragment_ms"] = gpu_ms(proc.run)
                part, block = proc.parts[0], proc.layout.parts[0]
                viewport = (0, 0, proc.layout.width, proc.layer_rows)

                def into(framebuffer):
                    framebuffer.viewport = viewport
                    framebuffer.use()
                    proc.layers_texture.use(3)

                def locals_pass():
                    into(proc._locals_framebuffer)
                    proc._draw_part(part, block, 0, part.locals_program)

                def compose_pass():
                    into(proc._framebuffer)
                    for unit, plane in zip(LOCALS_UNITS, proc._locals):
                        plane.use(unit)
                    proc._draw_part(part, block, 0, part.program)

                targets = {3: proc._locals_framebuffer, 1: scratch.add(ctx.framebuffer(color_attachments=[proc._locals[0]]))}
                vaos = {k: scratch.add(ctx.vertex_array(p, [(part.quad, "3f", "in_position")])) for k, p in floors.items()}

                def floor(k):
                    into(targets[k])
                    floors[k]["u_first_layer"] = 0
                    vaos[k].render(moderngl.TRIANGLES, vertices=part.quad_vertices)

                ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND | moderngl.CULL_FACE)
                row.update(locals_ms=gpu_ms(locals_pass), compose_ms=gpu_ms(compose_pass), floor_3_targets_ms=gpu_ms(lambda: floor(3)),
                           floor_1_target_ms=gpu_ms(lambda: floor(1)), texels=int(block.count * block.width))
            rows.append({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()})
    return rows
