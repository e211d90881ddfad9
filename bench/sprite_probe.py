"""Small sprites through the graphics pipeline (issue 43, third session): `python -m bench.sprite_probe`.

875,000 flat-shaded sprites, 3 to 40 px tall (heights from a 1/distance spread between 60 and 800 m,
as a crowd's far band on a 1080-row screen), drawn in random depth order six ways. They are drawn as
instanced 4-vertex quads with and without the depth test, and with fragment shaders that discard or
write their depth (plain or `depth_greater`). They are also drawn as vertex-pulled 6-vertex quads, and
as point sprites. GPU time by timer query, the median of 10 draws after 2. What it showed on the H200 is
in docs/BENCHMARKS.md ("Splatting the smallest impostors"): the graphics pipeline's cost there is per
instance and per sample, not per shader instruction.
"""

from __future__ import annotations

import argparse

import numpy as np

FLAT = "out vec4 o_color;\nvoid main() { o_color = vec4(1.0); }\n"
SPRITES = "#version 430\nlayout(std430, binding = 0) readonly buffer Sprites { vec4 sprite[]; };  // (x, y, z, width), (height, 0, 0, 0)\n"
QUAD_VS = SPRITES + """in vec2 in_corner;
out vec2 v_corner;
void main() {
    vec4 a = sprite[2 * gl_InstanceID];
    vec4 b = sprite[2 * gl_InstanceID + 1];
    v_corner = in_corner;
    gl_Position = vec4(a.x + (in_corner.x - 0.5) * a.w, a.y + in_corner.y * b.x, a.z, 1.0);
}
"""
PULLED_VS = SPRITES + """const vec2 CORNERS[6] = vec2[6](vec2(0, 0), vec2(1, 0), vec2(1, 1), vec2(0, 0), vec2(1, 1), vec2(0, 1));
void main() {
    vec2 c = CORNERS[gl_VertexID % 6];
    vec4 a = sprite[2 * (gl_VertexID / 6)];
    vec4 b = sprite[2 * (gl_VertexID / 6) + 1];
    gl_Position = vec4(a.x + (c.x - 0.5) * a.w, a.y + c.y * b.x, a.z, 1.0);
}
"""
POINT_VS = SPRITES + """uniform float u_half_height;
void main() {
    vec4 a = sprite[2 * gl_VertexID];
    vec4 b = sprite[2 * gl_VertexID + 1];
    gl_Position = vec4(a.x, a.y + 0.5 * b.x, a.z, 1.0);
    gl_PointSize = max(b.x * u_half_height, 1.0);
}
"""
FRAGMENTS = {
    "flat": FLAT,
    "discard": "in vec2 v_corner;\nout vec4 o_color;\nvoid main() { if (v_corner.x > 0.9) discard; o_color = vec4(1.0); }\n",
    "depth write": "out vec4 o_color;\nvoid main() { gl_FragDepth = gl_FragCoord.z + 1e-4; o_color = vec4(1.0); }\n",
    "depth write, depth_greater": "layout(depth_greater) out float gl_FragDepth;\nout vec4 o_color;\n"
                                  "void main() { gl_FragDepth = gl_FragCoord.z + 1e-4; o_color = vec4(1.0); }\n",
}


def sprites(count: int, size: tuple[int, int], seed: int = 1) -> np.ndarray:
    """(count, 8) float32: each sprite's (x, y, z, width) and (height, 0, 0, 0), in clip units."""
    rng = np.random.default_rng(seed)
    focal = 0.5 * size[1] / np.tan(np.radians(22.5))
    distance = np.exp(rng.uniform(np.log(60.0), np.log(800.0), count))
    height = 1.8 * focal / distance
    out = np.zeros((count, 8), np.float32)
    out[:, 0] = rng.uniform(-1.0, 1.0, count)
    out[:, 1] = rng.uniform(-0.1, 0.3, count)
    out[:, 2] = (distance - 60.0) / 800.0
    out[:, 3] = 0.42 * height * 2.0 / size[0]
    out[:, 4] = height * 2.0 / size[1]
    return out


def measure(ctx, count: int = 875_000, size: tuple[int, int] = (1920, 1080), repeats: int = 10) -> list[dict]:
    import moderngl

    from crowd.gl import GLObjects

    objects = GLObjects()
    try:
        data = objects.add(ctx.buffer(sprites(count, size).tobytes()))
        target = objects.add(ctx.framebuffer([objects.add(ctx.texture(size, 4))], objects.add(ctx.depth_texture(size))))
        corners = objects.add(ctx.buffer(np.array([0, 0, 1, 0, 0, 1, 1, 1], np.float32).tobytes()))
        query = ctx.query(time=True, samples=True)  # (moderngl's queries have no release: collected with the object)

        def program(vertex: str, fragment: str):
            return objects.add(ctx.program(vertex_shader=vertex, fragment_shader="#version 430\n" + fragment))

        quads = {name: objects.add(ctx.vertex_array(program(QUAD_VS, fs), [(corners, "2f", "in_corner")])) for name, fs in FRAGMENTS.items()}
        pulled = objects.add(ctx.vertex_array(program(PULLED_VS, FLAT), []))
        point_program = program(POINT_VS, FLAT)
        point_program["u_half_height"] = 0.5 * size[1]
        points = objects.add(ctx.vertex_array(point_program, []))
        cases = [(f"instanced quads, {name}", True, lambda vao=vao: vao.render(moderngl.TRIANGLE_STRIP, vertices=4, instances=count))
                 for name, vao in quads.items()]
        cases += [("instanced quads, flat, no depth test", False, lambda: quads["flat"].render(moderngl.TRIANGLE_STRIP, vertices=4, instances=count)),
                  ("vertex-pulled quads, flat", True, lambda: pulled.render(moderngl.TRIANGLES, vertices=6 * count)),
                  ("point sprites, flat", True, lambda: points.render(moderngl.POINTS, vertices=count))]
        data.bind_to_storage_buffer(0)
        ctx.enable(moderngl.PROGRAM_POINT_SIZE)
        rows = []
        for name, depth_test, draw in cases:
            (ctx.enable if depth_test else ctx.disable)(moderngl.DEPTH_TEST)
            target.use()
            times = []
            for _ in range(repeats + 2):
                target.clear(depth=1.0)
                with query:
                    draw()
                ctx.finish()
                times.append(query.elapsed / 1e6)
            rows.append({"case": name, "gpu_ms": round(float(np.median(times[2:])), 3), "samples": int(query.samples)})
        ctx.disable(moderngl.DEPTH_TEST | moderngl.PROGRAM_POINT_SIZE)
        return rows
    finally:
        objects.release()


def main(argv=None) -> int:
    from crowd.gl import describe, headless_context

    parser = argparse.ArgumentParser(prog="python -m bench.sprite_probe", description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=875_000, help="sprites")
    args = parser.parse_args(argv)
    ctx = headless_context(430)
    print(describe(ctx))
    for row in measure(ctx, args.count):
        print(f"{row['case']:<44} {row['gpu_ms']:>8.3f} ms {row['samples']:>12} samples passed")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
