"""The panel fits its window: at 1280x720 and larger its text never runs past its right edge (ImGui's
content width of the panel stays within the panel), with its default sections open it needs no
scrolling, and it sizes with the window. Drawn offscreen by the same code the window runs
(app.overlay.HeadlessPanel), on the headless loop's pipeline."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import gl_census
from crowd.gl import Offscreen
from crowd.pipeline import CrowdPipeline
from crowd.scene import Scene
from crowd.smoke import FIXED_DT

imgui_bundle = pytest.importorskip("imgui_bundle")
from imgui_bundle import imgui  # noqa: E402

from app.overlay import HeadlessPanel  # noqa: E402
from app.panel import MARGIN, OPEN_AT_START, SECTIONS  # noqa: E402


def _frames(target, pipeline, panel, count=3):
    for _ in range(count):
        pipeline.frame(target.framebuffer, FIXED_DT)
        panel.draw(target.framebuffer, FIXED_DT)


def _window():
    window = imgui.internal.find_window_by_name("crowd")
    assert window is not None
    region = window.content_region_rect
    return {"width": window.size.x, "height": window.size.y, "bottom": window.pos.y + window.size.y,
            "content_w": window.content_size_ideal.x, "region_w": region.get_width(), "scroll_y": window.scroll_max.y}


@pytest.fixture(scope="module")
def scene():
    # Two characters (the combo shows), weapons and foot lock on; the compressed bake adds its lines.
    return Scene(agents=60, precision="compressed")


@pytest.mark.parametrize("size", [(1280, 720), (1920, 1080), (2560, 1440)])
def test_the_panel_fits_the_window_folded_and_unfolded(gl_context, scene, size):
    with Offscreen(gl_context, size) as target, CrowdPipeline(gl_context, scene.pipeline_config()) as pipeline:
        pipeline.camera = pipeline.default_camera(size[0] / size[1])
        with HeadlessPanel(gl_context, pipeline, size, scene) as panel:
            _frames(target, pipeline, panel)
            folded = _window()
            # Default sections open: no scrolling, nothing past the right edge, inside the display.
            assert set(OPEN_AT_START) < set(SECTIONS)
            assert folded["scroll_y"] == 0 and folded["content_w"] <= folded["region_w"] + 0.5, folded
            assert folded["bottom"] <= size[1] - MARGIN + 0.5, folded
            # Everything open, an agent selected, a long refusal in the status line: it scrolls, yet no line
            # runs past the right edge.
            panel.session.selected = 3
            panel.overlay.panel.apply("clip_speed", pipeline.cast[0].bake.clips[0].name, -1.0)
            assert panel.overlay.panel.status
            panel.overlay.panel.open_sections(*SECTIONS)
            _frames(target, pipeline, panel)
            unfolded = _window()
            assert unfolded["content_w"] <= unfolded["region_w"] + 0.5, unfolded
            assert unfolded["bottom"] <= size[1] - MARGIN + 0.5 and unfolded["scroll_y"] > 0, unfolded
            # The panel is drawn: its corner is the panel's dark background over the bright town.
            image = target.image().astype(np.float64)
            inside = image[int(MARGIN) + 40:int(unfolded["bottom"]) - 10, int(MARGIN) + 10:int(MARGIN + unfolded["width"]) - 10]
            assert inside.mean() < image[:, int(MARGIN + unfolded["width"]) + 10:].mean()


def test_the_panel_sizes_with_the_window_and_releases_what_it_made(gl_context, scene):
    with Offscreen(gl_context, (1920, 1080)) as target, CrowdPipeline(gl_context, scene.pipeline_config()) as pipeline:
        pipeline.camera = pipeline.default_camera(16 / 9)
        for _ in range(3):  # the pipeline's own objects made at its first frames
            pipeline.frame(target.framebuffer, FIXED_DT)
        before = gl_census()
        with HeadlessPanel(gl_context, pipeline, (1920, 1080), scene) as panel:
            _frames(target, pipeline, panel)
            wide = _window()
            imgui.get_io().display_size = imgui.ImVec2(1280, 720)  # the window made smaller
            _frames(target, pipeline, panel)
            narrow = _window()
            imgui.get_io().display_size = imgui.ImVec2(1280, 400)  # shorter than the panel: it scrolls, inside the window
            _frames(target, pipeline, panel)
            short = _window()
        assert wide["width"] > narrow["width"] >= 360
        assert short["bottom"] <= 400 - MARGIN + 0.5 and short["scroll_y"] > 0
        assert short["content_w"] <= short["region_w"] + 0.5
        pipeline.frame(target.framebuffer, FIXED_DT)  # the pipeline, adopted, goes on after the panel's release
        assert {k: len(v) for k, v in gl_census().items()} == {k: len(v) for k, v in before.items()}


def test_a_panel_that_fails_half_built_leaves_nothing(gl_context, scene, monkeypatch):
    """moderngl-window's ImGui renderer failing inside its constructor (after its program and buffers
    exist): the error goes on, and no GL object or ImGui context is left behind."""
    import moderngl_window.integrations.imgui_bundle as integration

    with Offscreen(gl_context, (320, 180)) as target, CrowdPipeline(gl_context, scene.pipeline_config()) as pipeline:
        for _ in range(3):
            pipeline.frame(target.framebuffer, FIXED_DT)
        before = gl_census()

        def fails(self):
            raise RuntimeError("injected")

        monkeypatch.setattr(integration.ModernGLRenderer, "refresh_font_texture", fails)
        with pytest.raises(RuntimeError, match="injected"):
            HeadlessPanel(gl_context, pipeline, (320, 180), scene)
        assert {k: len(v) for k, v in gl_census().items()} == {k: len(v) for k, v in before.items()}
        assert imgui.get_current_context() is None
