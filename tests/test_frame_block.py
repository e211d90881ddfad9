"""The frame's constants in one uniform block (crowd.draw.frame_block, shaders/frame.glsl): its data
has the layout the shaders declare, a moving camera writes the block and no program's uniforms, and a
frame drawn after the camera moved is the picture a fresh crowd draws from there."""

from __future__ import annotations

import collections
import dataclasses

import numpy as np

from bench.gl_calls import counting_gl_calls
from crowd.draw.frame_block import FRAME_DEFINES, frame_constants
from crowd.draw.view import FrameView
from crowd.frame import Camera
from crowd.gl import Offscreen, load_shader
from crowd.pipeline import CrowdPipeline
from crowd.scene import Scene

SIZE = (160, 90)


def test_the_blocks_data_is_the_size_the_shaders_declare(gl_context):
    prog = gl_context.program(vertex_shader=load_shader("ground.vert.glsl", FRAME_DEFINES),
                              fragment_shader=load_shader("ground.frag.glsl", {**FRAME_DEFINES, "SHADOWS": 1}))
    try:
        view = FrameView(Camera((0.0, 2.0, 5.0), (0.0, 1.0, 0.0)), np.eye(4, dtype=np.float32), None, None)
        assert prog["Frame"].size == frame_constants(view, 0.004).nbytes
    finally:
        prog.release()


def _moved(camera: Camera, metres: float) -> Camera:
    eye = np.asarray(camera.eye, np.float64) + (metres, 0.0, 0.0)
    return dataclasses.replace(camera, eye=tuple(eye))


def test_a_moving_camera_writes_the_block_and_no_programs_uniforms(gl_context, monkeypatch):
    import _moderngl

    written: list[str] = []
    write = _moderngl.Uniform.write
    monkeypatch.setattr(_moderngl.Uniform, "write", lambda self, data: (written.append(self.name), write(self, data))[1])
    scene = Scene(agents=40, town=True, survivor=False, ai_path="cpu")
    with Offscreen(gl_context, SIZE) as target, CrowdPipeline(gl_context, scene.pipeline_config()) as p:
        start = p.overview_camera(SIZE[0] / SIZE[1])
        p.camera = start
        for _ in range(4):
            p.frame(target.framebuffer, 0.0)
        names, counts = [], []
        for moved in (0.0, 0.0, 0.5, 1.0):  # still, still, then moving
            p.camera = _moved(start, moved)
            written.clear()
            with counting_gl_calls() as gl:
                p.frame(target.framebuffer, 0.0)
            names.append(collections.Counter(written))
            counts.append(gl)
        # What a move adds: the block, and the camera-relative constants of the programs that alone read them
        # (the cull's frustum, the town's anchor); no camera or light uniform of any lit program.
        assert set(names[3] - names[1]) <= {"u_planes", "u_reach", "u_anchor_rel"}
        assert counts[3]["Buffer.write"] == counts[1]["Buffer.write"] + 1


def test_after_the_camera_moves_the_picture_is_a_fresh_crowds(gl_context):
    scene = Scene(agents=30, town=False, survivor=False, ai_path="cpu")
    pictures = []
    with Offscreen(gl_context, SIZE) as target:
        for moves in ((0.0, 3.0), (3.0,)):
            with CrowdPipeline(gl_context, scene.pipeline_config()) as p:
                start = p.overview_camera(SIZE[0] / SIZE[1])
                for metres in moves:
                    p.camera = _moved(start, metres)
                    p.frame(target.framebuffer, 0.0)
                pictures.append(np.frombuffer(target.framebuffer.read(), np.uint8).copy())
    assert np.array_equal(pictures[0], pictures[1])
