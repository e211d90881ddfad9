"""The smallest impostors splatted by compute passes (crowd.draw.splat): the same picture as their quads,
independent of invocation order, only where it is used; and the weapons tiny impostors no longer hold."""

import numpy as np
import pytest

import crowd.draw.render as render
from crowd.draw.splat import HELD_PX, MAX_SIDE, SPLAT_PX
from crowd.gl import Offscreen, has_compute
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import PipelineConfig
from crowd.scene import Scene


@pytest.fixture
def gpu(gl_context):
    if not has_compute(gl_context):
        pytest.skip("no GL 4.3 here")
    return gl_context


def _picture(ctx, config, size, near: bool = False):
    """The third frame of `config` on the overview camera (or the default one, `near`), and the pipeline's
    splat counts (splatted, quads) and GPU bytes."""
    with Offscreen(ctx, size) as target, CrowdPipeline(ctx, config) as p:
        p.camera = p.default_camera(size[0] / size[1]) if near else p.overview_camera(size[0] / size[1])
        if near:
            p.renderer.set_impostor_distance(4.0)
        for _ in range(3):
            p.frame(target.framebuffer, 1 / 30)
        splat = p.renderer.splat
        counts = None if splat is None else np.frombuffer(splat.counts.read(), np.uint32)[:2].tolist()
        return target.image().astype(int), counts, p.renderer.gpu_bytes()["splat"], list(p.passes_run)


@pytest.mark.parametrize("near", [False, True])
def test_the_splat_draws_what_the_quads_draw(gpu, monkeypatch, near):
    """Far impostors (the overview: all of them splatted) and a mix (the default camera with impostors from
    4 m: the nearer stay quads) give the quads' picture to rounding: no pixel off by more than 8 of 255,
    and under 0.2 % off at all."""
    config = PipelineConfig(agents=3000, seed=2, impostors="on", weapons=False)
    size = (320, 180)
    monkeypatch.setattr(render, "SPLAT_PX", 0.0)
    quads, none, no_bytes, quad_passes = _picture(gpu, config, size, near)
    monkeypatch.setattr(render, "SPLAT_PX", SPLAT_PX)
    splatted, counts, splat_bytes, passes = _picture(gpu, config, size, near)
    print(f"near={near}: splatted, quads {counts}")
    assert none is None and no_bytes == 0 and "splat" not in quad_passes
    assert "splat" in passes and splat_bytes >= 3 * 4 * size[0] * size[1]
    assert counts[0] > 500 and (counts[1] > 50 if near else counts[1] == 0)
    differ = np.abs(quads - splatted).max(axis=-1)
    assert np.count_nonzero(differ > 8) == 0
    assert np.count_nonzero(differ) <= 0.002 * differ.size


def test_the_splat_is_the_same_in_every_run(gpu):
    """Two runs of one seed give the same pixels, bit for bit (ties at a depth go to the lowest record)."""
    config = PipelineConfig(agents=2000, seed=5, impostors="on", weapons=False)
    first, counts, _, _ = _picture(gpu, config, (256, 144))
    second, _, _, _ = _picture(gpu, config, (256, 144))
    assert counts[0] > 500
    assert np.array_equal(first, second)


def test_the_splat_is_made_only_where_it_draws(gpu):
    """No splat without impostors or off the gpu cull path; its pixel buffers follow the viewport, and a
    crowd of none or a million and back leaves its bytes where they were."""
    for config in (PipelineConfig(agents=500, seed=1, impostors="off"), PipelineConfig(agents=500, seed=1, impostors="on", cull="cpu")):
        with Offscreen(gpu, (64, 36)) as target, CrowdPipeline(gpu, config) as p:
            p.frame(target.framebuffer, 1 / 30)
            assert p.renderer.splat is None and p.renderer.gpu_bytes()["splat"] == 0 and "splat" not in p.passes_run
    with CrowdPipeline(gpu, PipelineConfig(agents=500, seed=1, impostors="on", weapons=False)) as p:
        sizes = []
        for size in ((64, 36), (128, 72), (64, 36)):
            with Offscreen(gpu, size) as target:
                p.camera = p.overview_camera(size[0] / size[1])
                p.frame(target.framebuffer, 1 / 30)
                sizes.append(p.renderer.gpu_bytes()["splat"])
        assert sizes[0] == sizes[2] < sizes[1]
        with Offscreen(gpu, (64, 36)) as target:
            for n in (0, 100_000, 500):
                p.set("agents", n)
                p.frame(target.framebuffer, 1 / 30)
            grown = p.renderer.gpu_bytes()["splat"]
        assert grown >= sizes[0]  # (the sorted lists keep the largest crowd's room, as the cull's entries do)
        # One pixel, and none (a minimised window's framebuffer): frames go on.
        with Offscreen(gpu, (1, 1)) as target:
            p.frame(target.framebuffer, 1 / 30)
            target.framebuffer.viewport = (0, 0, 0, 0)
            p.frame(target.framebuffer, 1 / 30)


def test_a_viewport_of_more_pixels_than_one_dispatch_row_is_cleared_whole(gpu):
    """A 4K view has more pixels than 65,535 work groups of 64 (what GL promises a dispatch dimension):
    the clear runs in rows, so every pixel no impostor covers stays empty."""
    size = (2100, 2100)  # 4,410,000 pixels: 68,907 groups
    with Offscreen(gpu, size) as target, CrowdPipeline(gpu, PipelineConfig(agents=300, seed=1, impostors="on", weapons=False)) as p:
        p.camera = p.overview_camera(1.0)
        p.frame(target.framebuffer, 1 / 30)
        assert gpu.error == "GL_NO_ERROR"
        depth = np.frombuffer(p.renderer.splat.pixels[0].read(), np.uint32)
        splatted = int(np.frombuffer(p.renderer.splat.counts.read(), np.uint32)[0])
        covered = int(np.count_nonzero(depth != 0xFFFFFFFF))
        assert depth.size == size[0] * size[1] and covered <= 64 * max(splatted, 1), (covered, splatted)


def test_a_quad_too_wide_for_the_splat_stays_a_quad():
    """MAX_SIDE bounds an invocation's pixels; the height rule alone would let a lying agent's wide quad
    through, so it is a separate check, and both are below the blend's threshold."""
    from crowd.draw.impostors import BLEND_PX

    assert 0.0 < SPLAT_PX <= BLEND_PX and MAX_SIDE >= 2 * SPLAT_PX


def test_tiny_impostors_hold_no_weapon_at_a_measured_error(gpu, monkeypatch):
    """An impostor whose bound spans under HELD_PX pixels drops its held weapon from the view: thousands
    of instances fewer, and the picture changes by at most 32 of 255 on under 0.2 % of its pixels."""
    config = Scene(town=False).with_overrides(agents=20000).pipeline_config()
    size = (480, 270)
    pictures = {}
    for held in (0.0, HELD_PX):
        monkeypatch.setattr(render, "HELD_PX", held)
        with Offscreen(gpu, size) as target, CrowdPipeline(gpu, config) as p:
            p.camera = p.overview_camera(size[0] / size[1])
            for _ in range(3):
                p.frame(target.framebuffer, 1 / 60)
            p.refresh_counts()
            pictures[held] = (target.image().astype(int), p.renderer.last["instances"])
    (every, held_all), (fewer, held_fewer) = pictures[0.0], pictures[HELD_PX]
    differ = np.abs(every - fewer).max(axis=-1)
    print(f"instances {held_all} -> {held_fewer}; pixels off by > 8: {np.count_nonzero(differ > 8)} of {differ.size}")
    assert held_all - held_fewer > 2000
    assert np.count_nonzero(differ > 32) == 0 and np.count_nonzero(differ > 8) <= 0.002 * differ.size
