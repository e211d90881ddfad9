"""A million agents on the default path of llvmpipe (the GPU cull on its GL 4.5), whose shader storage blocks
hold 128 MB: the cull's lists fit at 64 bytes an agent or less; and on a driver whose blocks hold less (the
GL 4.3 minimum, 16 MB) the crowd is refused in one line that says what it needed and what avoids it."""

from __future__ import annotations

import numpy as np
import pytest

from crowd.draw.render import RenderError
from crowd.gl import Offscreen, has_compute
from crowd.pipeline import CrowdPipeline
from crowd.scene import Scene
from crowd.smoke import FIXED_DT

MILLION = 1_000_000


@pytest.fixture(scope="module")
def million(gl_context):
    if not has_compute(gl_context):
        pytest.skip("the default path of a GL 4.3 context")
    with CrowdPipeline(gl_context, Scene().with_overrides(agents=MILLION).pipeline_config()) as pipeline:
        yield pipeline


def test_a_million_agents_run_on_the_default_path(gl_context, million):
    assert million.renderer.cull_path == "gpu" and million.renderer.gpu.max_block == 128 << 20
    with Offscreen(gl_context, (160, 90)) as target:
        for _ in range(2):
            million.frame(target.framebuffer, FIXED_DT)
        million.renderer.refresh_counts(wait=True)
        image = target.image()
    held = million.renderer.gpu_bytes()
    rows = sum(million.counts)
    assert rows == MILLION + 1  # and the survivor
    assert held["lists"] <= 64 * rows and held["records"] == 32 * rows
    last = million.renderer.last
    assert last["visible"] > 0 and last["instances"] > 0 and np.ptp(image) > 0


def test_a_driver_with_smaller_storage_blocks_refuses_the_million_in_one_line(gl_context, million, monkeypatch):
    monkeypatch.setattr(million.renderer.gpu, "max_block", 16 << 20)
    monkeypatch.setattr(million.renderer.gpu, "cast", None)  # sized again on the next frame
    with Offscreen(gl_context, (32, 18)) as target, pytest.raises(RenderError) as refused:
        million.frame(target.framebuffer, FIXED_DT)
    line = str(refused.value)
    assert "\n" not in line and "1,000,001 agents need" in line and "16,777,216" in line and "--cull" in line


def test_the_default_picture_at_a_million_holds_more_agents_than_at_100000(gl_context, million):
    """From 10,000 agents the headless default is the horizon view (crowd.cameras): the same framing of
    a horde of constant density, so a million shows about ten times the agents of 100,000, most as
    impostors; the stats' "drawn" says how many of each."""
    from crowd.stats import pipeline_stats

    def drawn(pipeline) -> dict:
        pipeline.camera = pipeline.default_camera(16 / 9)
        with Offscreen(gl_context, (160, 90)) as target:
            for _ in range(2):
                pipeline.frame(target.framebuffer, FIXED_DT)
        pipeline.refresh_counts()
        return pipeline_stats(pipeline)["drawn"]

    with CrowdPipeline(gl_context, Scene().with_overrides(agents=100_000).pipeline_config()) as smaller:
        hundred_k = drawn(smaller)
    a_million = drawn(million)
    assert a_million["impostors"] > 0 and a_million["meshes"] + a_million["impostors"] > 4 * (hundred_k["meshes"] + hundred_k["impostors"])
