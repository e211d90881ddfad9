"""crowd-bench feedback: the transform-feedback cull (GL 4.0 to 4.2, crowd/draw/feedback_cull.py) against the
compute cull (GL 4.3), GPU ms (issue 25, point 2).

For each agent count, the built-in zombie on the benchmarks' grid (every agent in view, at every LOD), shadows
on (two cascades), a 2 m LOD fade and the weapons' visibility kept: the GPU time of the renderer's whole cull
(``CrowdRenderer.cull``: every list of the colour pass and the cascades, the counts turned into commands,
the stats' census and the visibility texture), the median of `repeats` runs, for the compute cull and the
feedback cull; the feedback cull with its counts spread over blocks of 4 x 4 texels a list instead of
COUNT_BLOCK x COUNT_BLOCK (how much points blended into one texel wait for one another); and its feedback
draws alone (no counting, commands or visibility).
"""

from __future__ import annotations

import contextlib
from unittest import mock

import numpy as np

from .common import grid_crowd

VARIANTS = ("compute", "feedback", "feedback_block_4", "feedback_draws_alone")


def measure(ctx, counts: list[int], repeats: int = 20) -> list[dict]:
    import crowd.draw.feedback_cull as feedback
    from crowd.asset.gltf import load_character
    from crowd.draw.render import CrowdRenderer
    from crowd.frame import Instances
    from crowd.gl import has_compute

    character = load_character(None)
    query = ctx.query(time=True)  # (a moderngl query has no release: the context frees it)

    def gpu_ms(renderer, camera, instances) -> float:
        samples = []
        for _ in range(repeats + 2):  # (the first runs compile and grow the lists)
            renderer.prepare(camera, instances, cull_now=False)
            with query:
                renderer.cull()
            samples.append(query.elapsed / 1e6)
        return float(np.median(samples[2:]))

    rows = []
    for n in counts:
        positions, camera = grid_crowd(n, 16 / 9)
        rng = np.random.default_rng(1)
        instances = Instances(positions, rng.uniform(-np.pi, np.pi, n).astype(np.float32), np.ones(n, np.float32),
                              np.full((n, 4), 255, np.uint8), {"head": rng.integers(0, 2, n)})
        row = {"agents": n}
        for name in VARIANTS:
            if name == "compute" and not has_compute(ctx):
                continue
            with contextlib.ExitStack() as stack:
                if name == "feedback_block_4":
                    stack.enter_context(mock.patch.object(feedback, "COUNT_BLOCK", 4))
                if name == "feedback_draws_alone":
                    for owner, method in ((feedback.FeedbackCounter, "count_stream"), (feedback.FeedbackCounter, "finish"),
                                          (feedback.FeedbackCull, "_write_visible")):
                        stack.enter_context(mock.patch.object(owner, method, lambda *args, **kwargs: None))
                renderer = stack.enter_context(CrowdRenderer(ctx, character, shadows=True, culling=True, cull_path="gpu" if name == "compute" else "feedback",
                                                             weapons_visibility=True, lod_fade=2.0))
                row[f"{name}_ms"] = round(gpu_ms(renderer, camera, instances), 4)
                if name in ("compute", "feedback"):
                    renderer.refresh_counts(wait=True)
                    row[f"{name}_listed"] = renderer.last["instances"] + renderer.last["shadow_instances"]
                if name == "feedback":
                    row["feedback_draws"] = len(renderer.feedback.groups)
                    row["lists"] = len(renderer.feedback.slots)
        rows.append(row)
    return rows


FLOOR_VS = """#version 410 core
in vec4 in_p; in uvec4 in_f;
uniform vec4 u_planes[6];
uniform float u_keep;  // the share of points kept
flat out int v_emit; out vec4 v_p; flat out uvec4 v_f;
void main() {
    bool inside = true;
    for (int k = 0; k < 6; ++k) inside = inside && dot(u_planes[k].xyz, in_p.xyz) + u_planes[k].w >= -1.0;
    float d = length(in_p.xyz);
    v_emit = int(inside && fract(d * 0.37) < u_keep);
    v_p = in_p; v_f = in_f;
    gl_Position = v_emit == 1 ? vec4(fract(d) * 2.0 - 1.0, 0.0, 0.0, 1.0) : vec4(2.0, 2.0, 2.0, 1.0);
}
"""
FLOOR_GS = """#version 410 core
layout(points) in; layout(points, max_vertices = 1) out;
flat in int v_emit[]; in vec4 v_p[]; flat in uvec4 v_f[];
out vec4 f_p; flat out uvec4 f_f;
void main() {
    if (v_emit[0] == 0) return;
    f_p = v_p[0]; f_f = v_f[0];
    gl_Position = vec4(float(gl_PrimitiveIDIn & 63) / 32.0 - 0.99, 0.0, 0.0, 1.0);
    EmitVertex();
}
"""


def floor(ctx, n: int = 1_000_000, repeats: int = 6) -> dict:
    """What a point draw of `n` 32-byte records costs, by kind, a quarter of the points kept, the rasterizer
    off: with transform feedback active (a geometry shader emitting the kept records, or the vertex
    shader's every output captured), a geometry shader without feedback, and a plain point draw. GPU ms,
    the median of `repeats` runs of 4 draws each, per draw."""
    import moderngl

    from crowd.draw.feedback_cull import TransformFeedbacks, capture
    from crowd.gl import GLObjects

    rng = np.random.default_rng(1)
    records = np.zeros(n, [("p", "<f4", 4), ("f", "<u4", 4)])
    records["p"][:, :3] = rng.uniform(-100, 100, (n, 3))
    records["f"] = rng.integers(0, 1 << 30, (n, 4))
    planes = np.array([[1, 0, 0, 100], [-1, 0, 0, 100], [0, 1, 0, 100], [0, -1, 0, 100], [0, 0, 1, 100], [0, 0, -1, 100]], np.float32)
    captured = FLOOR_VS.replace("out vec4 v_p; flat out uvec4 v_f;", "out vec4 f_p; flat out uvec4 f_f;").replace("v_p = in_p; v_f = in_f;", "f_p = in_p; f_f = in_f;")
    query = ctx.query(time=True)
    out = {}
    objects = GLObjects()
    try:
        source = objects.add(ctx.buffer(records.tobytes()))
        into = [objects.add(ctx.buffer(reserve=n * 36))]
        target = objects.add(ctx.framebuffer([objects.add(ctx.texture((64, 1), 1, dtype="f4"))]))
        kinds = {"feedback_geometry_shader": dict(vertex_shader=FLOOR_VS, geometry_shader=FLOOR_GS, varyings=["f_p", "f_f"]),
                 "feedback_vertex_shader": dict(vertex_shader=captured, varyings=["f_p", "f_f", "v_emit"]),
                 "geometry_shader": dict(vertex_shader=FLOOR_VS, geometry_shader=FLOOR_GS),
                 "points": dict(vertex_shader=FLOOR_VS)}
        feedbacks = objects.add(TransformFeedbacks(1))
        for name, stages in kinds.items():
            program = objects.add(ctx.program(**stages))
            if "u_planes" in set(program):
                program["u_planes"].write(planes.tobytes())
            if "u_keep" in set(program):
                program["u_keep"] = 0.25
            names = set(program)
            vao = objects.add(ctx.vertex_array(program, [(source, "4f 4u", "in_p", "in_f")] if "in_f" in names else [(source, "4f 16x", "in_p")]))
            target.use()
            ctx.enable(moderngl.RASTERIZER_DISCARD)
            samples = []
            for _ in range(repeats + 2):
                with query:
                    for _ in range(4):
                        if name.startswith("feedback"):
                            capture(program, vao, feedbacks[0], into, 0, n)
                        else:
                            vao.render(moderngl.POINTS, vertices=n)
                samples.append(query.elapsed / 1e6 / 4)
            ctx.disable(moderngl.RASTERIZER_DISCARD)
            out[f"{name}_ms"] = round(float(np.median(samples[2:])), 4)
    finally:
        objects.release()
    return {"points": n, **out}
