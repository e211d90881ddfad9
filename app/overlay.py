"""The panel and the HUD drawn over a frame, by the window every frame and, when asked, by the headless
loop (``crowd-demo --headless --panel``, ``crowd-bench frame --panel``): where no window can open (the
H200 machine has no GLX), the panel's cost is measured in the offscreen frame, through the same code."""

from __future__ import annotations

import time
from pathlib import Path

import moderngl

from crowd.gl import GLStage, import_moderngl_window
from crowd.pipeline import CrowdPipeline
from crowd.scene import Scene
from crowd.session import CrowdSession

from .camera import FollowControl
from .hud import draw_hud
from .panel import Panel


class Overlay:
    """The ImGui frame: the HUD and the panel, rendered by `gui` (a moderngl-window ImGui renderer)."""

    def __init__(self, gui, session: CrowdSession, scene_path: Path | None):
        from imgui_bundle import imgui

        self.imgui = imgui
        self.gui = gui
        self.session = session
        self.panel = Panel(session, scene_path)
        self.hud_shown: dict | None = None  # what the HUD showed last (the window test reads it)

    def draw(self, framebuffer, frame_seconds: float) -> None:
        """One ImGui frame over `framebuffer`; `frame_seconds` is the frame's period (the panel plots it)."""
        imgui = self.imgui
        io = imgui.get_io()
        io.delta_time = max(float(frame_seconds), 1e-6)  # ImGui refuses a frame without time passing
        self.panel.record_frame(frame_seconds)
        imgui.new_frame()
        self.hud_shown = draw_hud(imgui, self.session.hud(), io.display_size.x)
        self.panel.draw()
        imgui.render()
        framebuffer.use()
        self.gui.render(imgui.get_draw_data())


def _renderer(base, ctx: moderngl.Context, size: tuple[int, int]):
    """moderngl-window's ImGui renderer, which on a failure half-way through its constructor keeps what it
    had made (its program, buffers, vertex array): released here before the error goes on."""

    class Renderer(base):
        def __init__(self):
            try:
                super().__init__(ctx=ctx, display_size=tuple(float(v) for v in size))
            except BaseException:
                self._invalidate_device_objects()
                raise

    return Renderer()


class HeadlessPanel(GLStage):
    """The overlay on the headless loop's pipeline (its session adopts the pipeline and leaves it to its
    owner). Owns the ImGui and ImPlot contexts and the renderer's GL objects, and releases them."""

    def __init__(self, ctx: moderngl.Context, pipeline: CrowdPipeline, size: tuple[int, int], scene: Scene, follow: bool = False):
        """`follow`: the window's third-person camera behind the survivor, from the next frame on (the demo's
        picture); off, the loop's camera stays (the benchmark compares the same view with and without).
        The loop steps the pipeline itself, and nobody clicks: the panel is drawn, its controls do nothing."""
        self.gui = self.session = None
        import_moderngl_window()  # first, without its PyGLM warning
        from imgui_bundle import imgui, implot
        from moderngl_window.integrations.imgui_bundle import ModernGLRenderer

        self._imgui, self._implot = imgui, implot
        self._context = imgui.create_context()
        imgui.get_io().set_ini_filename("")  # headless: no imgui.ini written where the run started
        self._plot_context = implot.create_context()
        self.gui = _renderer(ModernGLRenderer, ctx, size)
        self.session = CrowdSession(ctx, scene, size[0] / size[1], pipeline=pipeline)
        self.overlay = Overlay(self.gui, self.session, None)
        self.follow = FollowControl() if follow and pipeline.survivor is not None else None
        self.walls = FollowControl.walls_in(pipeline.obstacles) if self.follow is not None else None
        self._last: float | None = None

    @classmethod
    def factory(cls, scene: Scene, follow: bool = False):
        """What crowd.smoke.run_headless takes as its overlay: built once its pipeline exists."""
        return lambda ctx, pipeline, size: cls(ctx, pipeline, size, scene, follow)

    def draw(self, framebuffer, dt: float) -> None:
        if self.follow is not None:
            self.follow.apply(self.session.pipeline.camera, self.session.pipeline.survivor.position, self.walls)
        now = time.perf_counter()
        period = dt if self._last is None else now - self._last
        self._last = now
        self.overlay.draw(framebuffer, period)

    def release(self) -> None:
        if self.gui is not None:
            self.gui.shutdown()
            self.gui = None
        if self.session is not None:
            self.session.release()  # the pipeline stays: it is the loop's
            self.session = None
        if getattr(self, "_plot_context", None) is not None:
            self._implot.destroy_context(self._plot_context)
            self._plot_context = None
        if getattr(self, "_context", None) is not None:
            self._imgui.destroy_context(self._context)
            self._context = None
