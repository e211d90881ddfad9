"""The GL call counter of crowd-bench frame (bench.gl_calls) counts what a frame issues and leaves
moderngl as it found it."""

from __future__ import annotations

import moderngl

from bench.gl_calls import counting_gl_calls


def test_the_counter_counts_each_call_and_restores_moderngl(gl_context):
    write, enter = moderngl.Buffer.write, moderngl.Query.__enter__
    buffer = gl_context.buffer(reserve=64)
    program = gl_context.program(vertex_shader="#version 330\nuniform float u_x;\nvoid main() { gl_Position = vec4(u_x); }",
                                 fragment_shader="#version 330\nout vec4 c;\nvoid main() { c = vec4(1.0); }")
    try:
        with counting_gl_calls() as counts:
            for _ in range(3):
                buffer.write(bytes(16))
            program["u_x"].value = 2.0
            program["u_x"].write(bytes(4))
        assert counts["Buffer.write"] == 3 and counts["Uniform.write"] == 2
        buffer.write(bytes(16))
        assert counts["Buffer.write"] == 3  # nothing counted after the block
        assert moderngl.Buffer.write is write and moderngl.Query.__enter__ is enter
    finally:
        buffer.release()
        program.release()
