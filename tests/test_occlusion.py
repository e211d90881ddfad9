"""Occlusion culling (crowd/draw/occlusion.py): the depth pyramid against a float64 reduction of the
depth it was built from, the agents it drops against the picture, and what exists only with it on."""

import numpy as np
import pytest

from crowd.frame import Camera
from crowd.gl import Offscreen
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import PipelineConfig
from crowd.sim.config import AIConfig

SIZE = (320, 180)


@pytest.fixture
def compute(compute_context):  # occlusion culling runs on the gpu cull path (GL 4.3)
    return compute_context


def _run(ctx, occlusion: bool, frames: int = 4, dt: float = 0.0, camera=None, **config):
    """A dense block of agents seen from inside it at knee height; returns (renderer.last, picture, pipeline facts)."""
    cfg = PipelineConfig(agents=4000, seed=2, occlusion=occlusion, weapons=config.pop("weapons", False),
                         ai=AIConfig(area_per_agent=0.4), **config)
    with CrowdPipeline(ctx, cfg) as p, Offscreen(ctx, SIZE) as target:
        h = p.ai.half_extent
        p.camera = camera or Camera(eye=np.array([-h + 1.0, 1.2, 0.0]), target=np.array([h, 1.0, 0.0]), fov_y=50.0, aspect=SIZE[0] / SIZE[1])
        for _ in range(frames):
            p.frame(target.framebuffer, dt)
        ctx.finish()
        p.refresh_counts()
        facts = {"passes": list(p.passes_run), "bytes": p.gpu_bytes(), "pyramid": p.renderer.pyramid}
        if p.renderer.pyramid is not None:
            py = p.renderer.pyramid
            facts["depth"] = np.frombuffer(py.depth.read(), np.float32).reshape(SIZE[1], SIZE[0]).astype(np.float64)
            facts["levels"] = [np.frombuffer(py.pyramid.read(level=k), np.float32).reshape(h_, w_) for k, (w_, h_) in enumerate(py.levels)]
        return dict(p.renderer.last), target.image().astype(int), facts


def test_the_pyramid_holds_the_farthest_depth_of_what_it_covers(compute):
    """Each texel of each level equals the maximum of the texels it covers one level finer (the last
    row and column of an odd level take the extra one in), computed here in float64. Level 0 reduces
    the depth copy, which the shader and a read-back turn from 24-bit depth into floats each their own
    way: within one 24-bit step of it; the levels after it exactly."""
    _, _, facts = _run(compute, True, frames=2)
    finer = facts["depth"]
    for k, level in enumerate(facts["levels"]):
        h, w = level.shape
        ys = [slice(2 * y, 2 * y + 2 + (1 if y == h - 1 and finer.shape[0] % 2 else 0)) for y in range(h)]
        xs = [slice(2 * x, 2 * x + 2 + (1 if x == w - 1 and finer.shape[1] % 2 else 0)) for x in range(w)]
        expected = np.array([[finer[sy, sx].max() for sx in xs] for sy in ys])
        if k == 0:
            np.testing.assert_allclose(level, expected, rtol=0, atol=1.0 / (1 << 24))
        else:
            np.testing.assert_array_equal(level, expected.astype(np.float32))
        finer = level.astype(np.float64)
    assert facts["levels"][-1].shape == (1, 1) and 0.0 < facts["levels"][-1][0, 0] <= 1.0


def test_hidden_agents_are_dropped_and_the_picture_is_the_same(compute):
    """A still crowd (dt 0): more than a third of the agents in the frustum are hidden behind the
    first rows, and the picture with occlusion culling is the picture without it, to the bit."""
    off, picture_off, facts_off = _run(compute, False)
    on, picture_on, facts_on = _run(compute, True)
    assert on["visible"] < 0.66 * off["visible"] and on["instances"] < off["instances"]
    assert np.array_equal(picture_on, picture_off)
    # The pyramid, its pass and its bytes exist only with occlusion on.
    assert "hiz" in facts_on["passes"] and "hiz" not in facts_off["passes"]
    assert facts_on["bytes"]["occlusion"] > SIZE[0] * SIZE[1] * 4 and "occlusion" not in facts_off["bytes"]


def test_a_moving_crowd_keeps_its_picture_but_for_agents_coming_into_view(compute):
    """Walking agents (the default time step): agents that come out from behind others are drawn a
    frame late, so the pictures may differ, but only in a sliver of the frame."""
    off, picture_off, _ = _run(compute, False, frames=8, dt=1 / 30)
    on, picture_on, _ = _run(compute, True, frames=8, dt=1 / 30)
    differ = (np.abs(picture_on - picture_off).max(axis=2) > 8).mean()
    assert on["visible"] < off["visible"] and differ < 0.01, differ


def test_the_cpu_path_and_a_toggle_leave_no_pyramid(compute):
    _, _, facts = _run(compute, True, frames=1, cull="cpu")
    assert facts["pyramid"] is None and "hiz" not in facts["passes"]
    with CrowdPipeline(compute, PipelineConfig(agents=50, occlusion=True, weapons=False)) as p, Offscreen(compute, SIZE) as target:
        p.frame(target.framebuffer, 1 / 60)
        assert p.renderer.pyramid is not None
        pyramid = p.renderer.pyramid
        p.set("occlusion", False)
        assert p.renderer.pyramid is None and pyramid.pyramid is None and "occlusion" not in p.gpu_bytes()
        p.set("occlusion", True)
        p.frame(target.framebuffer, 1 / 60)
        p.frame(target.framebuffer, 1 / 60)
        assert p.gpu_bytes()["occlusion"] > 0


def test_a_depth_that_cannot_be_copied_turns_occlusion_off_and_culls_nothing(compute):
    """Where the blit fails (a depth format the copy cannot take), the pyramid says why and the cull
    tests nothing against it: the crowd is drawn as with occlusion off."""
    from crowd.draw.occlusion import DepthPyramid

    class FailingBlit:
        def __init__(self, ctx):
            self._ctx, self.calls = ctx, 0

        def __getattr__(self, name):
            return getattr(self._ctx, name)

        @property
        def error(self):
            self.calls += 1
            return "GL_INVALID_OPERATION" if self.calls == 2 else "GL_NO_ERROR"  # the read after the blit

    off, _, _ = _run(compute, False)
    original = DepthPyramid.capture

    def failing(self, framebuffer, view_proj, eye):
        if not isinstance(self.ctx, FailingBlit):
            self.ctx = FailingBlit(self.ctx)
        return original(self, framebuffer, view_proj, eye)

    DepthPyramid.capture = failing
    try:
        on, _, facts = _run(compute, True)
    finally:
        DepthPyramid.capture = original
    assert "could not be copied (GL_INVALID_OPERATION)" in facts["pyramid"].unusable
    assert on["visible"] == off["visible"]
