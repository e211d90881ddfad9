"""The demo window: moderngl-window (pyglet) with the crowd, the ground, the player marker and the ImGui
panel. Thin: input is turned into CrowdSession calls, the panel into Panel actions.

Two cameras, toggled with C: a third-person camera that follows the survivor (the default where there
is one; drag turns it around the survivor, the wheel moves it in and out), and the orbit camera (left drag
orbits, middle drag or shift + left drag pans, the wheel zooms).
Mouse: a left click (without dragging) selects the zombie under the cursor, a right click sends the
player there. Keys: W/A/S/D move the player (relative to the camera; behind the survivor it faces where
the camera looks, so A and D strafe), space swings, C switches cameras, V shows the horizon view (high over
the horde's near edge, across it to its far side: crowd.cameras.horizon_camera) and back, P pauses, "."
steps one frame, H hides the panel. The HUD (app/hud.py) shows the survivor's health, kills, the zombies near it and the
round's time against the best.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

from crowd.gl import import_moderngl_window
from crowd.scene import Scene
from crowd.session import CrowdSession

from .camera import FollowControl, OrbitControl
from .markers import MarkerRings
from .overlay import Overlay

PLAYER_SPEED = 4.0  # m/s with W/A/S/D
MAX_FRAME_DT = 0.25
mglw = import_moderngl_window()


def config_dir() -> Path:
    """The user's configuration folder for crowd: %APPDATA% on Windows, ~/Library/Application Support on
    macOS, $XDG_CONFIG_HOME or ~/.config elsewhere."""
    if sys.platform == "win32" and os.environ.get("APPDATA"):
        return Path(os.environ["APPDATA"]) / "crowd"
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Application Support" / "crowd"
    return Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config") / "crowd"


def imgui_ini_path() -> str:
    """Where ImGui keeps the panel's layout between runs: imgui.ini in the user's configuration folder,
    never the working folder (ImGui's default); "" (kept nowhere) where that folder cannot be made."""
    try:
        folder = config_dir()
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return ""
    return str(folder / "imgui.ini")


class CrowdWindow(mglw.WindowConfig):
    # 3.3 core, forward-compatible: macOS answers with its 4.1 core, Linux drivers with their newest core
    # version; what the frame then uses follows the context (crowd.gl.has_compute) and the "gl" setting.
    gl_version = (3, 3)
    title = "crowd: zombie horde"
    window_size = (1280, 720)
    aspect_ratio = None
    resizable = True
    vsync = True
    clear_color = None
    log_level = logging.WARNING  # moderngl-window logs its context and window at INFO: not a user's business
    # Set by open_window before the window exists (moderngl-window builds the instance itself).
    launch: dict = {}

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        from imgui_bundle import imgui, implot
        from moderngl_window.integrations.imgui_bundle import ModernglWindowRenderer

        self.imgui = imgui
        imgui.create_context()
        imgui.get_io().set_ini_filename(imgui_ini_path())
        implot.create_context()
        self.gui = ModernglWindowRenderer(self.wnd)
        width, height = self.wnd.buffer_size
        self.session = CrowdSession(self.ctx, self.launch["scene"], width / max(height, 1))
        try:
            self.markers = MarkerRings(self.ctx)
        except BaseException:
            self.session.release()
            raise
        self.overlay = Overlay(self.gui, self.session, self.launch.get("scene_path"))
        self.panel = self.overlay.panel
        self.orbit = OrbitControl(self.session.pipeline.camera)
        self.follow = FollowControl()
        self.walls = FollowControl.walls_in(self.session.pipeline.obstacles)
        self.camera_mode = "follow" if self.session.pipeline.survivor is not None else "orbit"
        self.horizon = False  # V: the horizon view in place of the follow or orbit camera, until V again
        self._steering = False  # whether the keys steered the survivor last frame
        self.keys_down: set = set()
        self._press = None  # where a left press started, to tell a click from a drag
        self._dragged = 0.0
        self.frame_period_ms: list[float] = []  # from one frame's start to the next: the swap paces it
        self._last_start: float | None = None

    # -- frames

    def on_render(self, time_s: float, frame_time: float) -> None:
        started = time.perf_counter()
        if self._last_start is not None:
            self.frame_period_ms.append((started - self._last_start) * 1e3)
        self._last_start = started
        dt = min(max(frame_time, 0.0), MAX_FRAME_DT)
        self._walk_player(dt)
        survivor = self.session.pipeline.survivor
        width, height = self.wnd.buffer_size
        camera = self.session.pipeline.camera
        if self.horizon:  # recomputed each frame: the crowd's extent follows its agent count
            view = self.session.pipeline.view_camera("horizon", width / max(height, 1))
            camera.eye, camera.target, camera.near, camera.far, camera.fog_reach = view.eye, view.target, view.near, view.far, view.fog_reach
        else:
            camera.near, camera.fog_reach = 0.1, None
            if self.camera_mode == "follow" and survivor is not None:
                self.follow.apply(camera, survivor.position, self.walls)
            else:
                self.orbit.apply(camera)
        camera.aspect = width / max(height, 1)
        fbo = self.wnd.fbo
        self.session.frame(fbo, dt)
        self.markers.draw(fbo, self.session.last.view, *self.session.markers())
        self.overlay.draw(fbo, frame_time if frame_time > 0 else dt)

    def _walk_player(self, dt: float) -> None:
        keys = self.wnd.keys
        step = np.zeros(2)
        for key, direction in ((keys.W, (0, -1)), (keys.S, (0, 1)), (keys.A, (-1, 0)), (keys.D, (1, 0))):
            if key in self.keys_down:
                step += direction
        # Screen-relative: W walks away from the camera.
        following = self.camera_mode == "follow" and self.session.pipeline.survivor is not None
        yaw = self.follow.yaw if following else self.orbit.yaw
        right = np.array([np.cos(yaw), -np.sin(yaw)])
        back = np.array([np.sin(yaw), np.cos(yaw)])
        direction = (step[0] * right + step[1] * back) / max(np.linalg.norm(step), 1e-12)
        if self.session.pipeline.survivor is not None:
            # The survivor runs where the keys point (behind it, facing where the camera looks: A and D strafe);
            # with no key down it stops, once, so a right click's run to a point goes on.
            if step.any() or self._steering:
                self.session.steer(direction if step.any() else (0.0, 0.0), self.follow.forward() if following and step.any() else None)
            self._steering = bool(step.any())
        elif step.any():
            self.session.move_player(self.session.pipeline.ai.player + direction * PLAYER_SPEED * dt)

    # -- input: ImGui first; the scene gets what the panel does not want

    def on_resize(self, width: int, height: int) -> None:
        self.gui.resize(width, height)

    def on_key_event(self, key, action, modifiers) -> None:
        self.gui.key_event(key, action, modifiers)
        keys = self.wnd.keys
        if action == keys.ACTION_RELEASE:
            self.keys_down.discard(key)
            return
        if action != keys.ACTION_PRESS or self.imgui.get_io().want_capture_keyboard:
            return
        self.keys_down.add(key)
        if key == keys.SPACE:
            self.session.strike()
        elif key == keys.C and self.session.pipeline.survivor is not None:
            self.horizon = False
            self._switch_camera()
        elif key == keys.V:
            self.horizon = not self.horizon
        elif key == keys.P:
            self.panel.apply("pause", not self.session.paused)
        elif key == keys.PERIOD:
            self.panel.apply("step")
        elif key == keys.H:
            self.panel.visible = not self.panel.visible

    def on_unicode_char_entered(self, char: str) -> None:
        self.gui.unicode_char_entered(char)

    def on_mouse_position_event(self, x, y, dx, dy) -> None:
        self.gui.mouse_position_event(x, y, dx, dy)

    def on_mouse_drag_event(self, x, y, dx, dy) -> None:
        self.gui.mouse_drag_event(x, y, dx, dy)
        if self.imgui.get_io().want_capture_mouse:
            return
        self._dragged += abs(dx) + abs(dy)
        states = self.wnd.mouse_states
        if self.camera_mode == "follow" and self.session.pipeline.survivor is not None:
            if states.left or states.middle:
                self.follow.orbit(dx, dy)
        elif states.middle or (states.left and self.wnd.modifiers.shift):
            self.orbit.pan(dx, dy)
        elif states.left:
            self.orbit.orbit(dx, dy)

    def on_mouse_scroll_event(self, x_offset, y_offset) -> None:
        self.gui.mouse_scroll_event(x_offset, y_offset)
        if not self.imgui.get_io().want_capture_mouse:
            (self.follow if self.camera_mode == "follow" else self.orbit).zoom(y_offset)

    def on_mouse_press_event(self, x, y, button) -> None:
        self.gui.mouse_press_event(x, y, button)
        if self.imgui.get_io().want_capture_mouse:
            return
        self._press, self._dragged = (x, y), 0.0
        if button == self.wnd.mouse.right:
            point = self.session.ground_point(*self._pixel(x, y), self.wnd.buffer_size)
            if point is not None:
                self.session.go_to(point)

    def on_mouse_release_event(self, x, y, button) -> None:
        self.gui.mouse_release_event(x, y, button)
        if self._press is not None and button == self.wnd.mouse.left and self._dragged < 4:
            self.session.pick(*self._pixel(x, y), self.wnd.buffer_size)
        self._press = None

    def _switch_camera(self) -> None:
        """Behind the survivor, or the orbit camera around where it stands (and back)."""
        if self.camera_mode == "follow":
            camera = self.session.pipeline.camera
            self.orbit = OrbitControl(camera)
            self.camera_mode = "orbit"
        else:
            self.camera_mode = "follow"

    def _pixel(self, x, y) -> tuple[float, float]:
        """Window coordinates to framebuffer pixels (they differ on high-DPI screens)."""
        ratio = self.wnd.pixel_ratio
        return x * ratio, y * ratio

    def release(self) -> None:
        """Everything the window made on the GPU; run_window calls it once the last stats are taken,
        however the window ended (closed by the user, or after --frames)."""
        self.markers.release()
        self.session.release()

    def screenshot(self, path: Path) -> None:
        from crowd.gl import read_image
        from crowd.images import write_png

        write_png(path, read_image(self.wnd.fbo, self.wnd.buffer_size))


def open_window(scene: Scene, size: tuple[int, int], scene_path: Path | None = None) -> CrowdWindow:
    """Make the window (pyglet) and everything in it; the caller runs frames with run_frames."""
    CrowdWindow.window_size = size
    CrowdWindow.launch = {"scene": scene, "scene_path": scene_path}
    return mglw.create_window_config_instance(CrowdWindow, args=["--window", "pyglet"])


def render_frame(window: CrowdWindow, dt: float | None = None) -> None:
    """One frame: events, render, swap. dt None uses the window's clock."""
    wnd = window.wnd
    current, delta = window.timer.next_frame()
    wnd.use()
    wnd.render(current, delta if dt is None else dt)
    wnd.swap_buffers()


def run_window(scene: Scene, size: tuple[int, int], frames: int | None, screenshot: Path | None, stats_path: Path | None,
               scene_path: Path | None) -> dict:
    """The interactive demo: until the window is closed, or for `frames` frames when given (scripts)."""
    from crowd.gl import describe
    from crowd.stats import collect_stats, write_stats

    window = open_window(scene, size, scene_path)
    window.timer.start()
    count = 0
    try:
        while not window.wnd.is_closing and (frames is None or count < frames):
            render_frame(window)
            count += 1
        window.session.pipeline.timer.end_frame(drain=True)
        if screenshot is not None:
            window.screenshot(screenshot)
        # The window never finishes a frame to time it (that would stall it), so it has no latency.
        stats = collect_stats(window.ctx, window.session.pipeline, {"frame_period_ms": window.frame_period_ms[1:]},
                              window.wnd.buffer_size, scene, len(window.frame_period_ms) + 1)
        stats["gpu_bytes"]["markers"] = window.markers.gpu_bytes()
        stats["window"] = {"backend": "pyglet", "frames": count, **describe(window.ctx)}
        if stats_path is not None:
            write_stats(stats_path, stats)
        return stats
    finally:
        window.release()
        window.wnd.destroy()
