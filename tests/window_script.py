"""Run by tests/test_window.py in a subprocess with DISPLAY pointing at an Xvfb server: opens the real
window, renders frames with the panel, changes clip settings through the panel's actions (the UI layer)
and saves screenshots. Prints one JSON line of what it saw."""

import json
import sys
from pathlib import Path

from app.window import open_window, render_frame
from crowd.sim.config import AIConfig
from crowd.scene import Scene

out = Path(sys.argv[1])
window = open_window(Scene(agents=60, ai=AIConfig(half_extent=9.0)), (800, 450))
panel, session = window.panel, window.session
for _ in range(5):
    render_frame(window, 1 / 30)
walk = session.pipeline.roles["walk"]
result = {
    "speed_ok": panel.apply("clip_speed", walk, 1.5),
    "loop_ok": panel.apply("clip_loop", "attack", True),
    "bad_refused": not panel.apply("clip_speed", walk, -2.0),
    "status": panel.status,
}
result["clip_speed"] = session.pipeline.clip_speed
result["attack_loops"] = session.pipeline.bake.clips[session.clip_names().index("attack")].loop
for _ in range(5):
    render_frame(window, 1 / 30)
window.screenshot(out / "with_panel.png")
panel.visible = False
render_frame(window, 0.0)
window.screenshot(out / "without_panel.png")
panel.apply("agents", 0)
render_frame(window, 0.0)
window.screenshot(out / "empty.png")
# Input as the window gets it: a right click moves the player, a left click selects, P pauses.
from moderngl_window.context.base import KeyModifiers  # noqa: E402

panel.apply("agents", 60)
render_frame(window, 1 / 30)
wnd = window.wnd
ai = session.pipeline.ai
before = ai.player.copy()
window.on_mouse_press_event(400, 300, wnd.mouse.right)
window.on_mouse_release_event(400, 300, wnd.mouse.right)
for _ in range(10):  # the survivor runs to the clicked point
    render_frame(window, 1 / 30)
result["player_moved"] = float(abs(session.pipeline.ai.player - before).max())
import numpy as np  # noqa: E402

if session.pipeline.gpu_crowd is not None:  # a crowd on the GPU: where its agents stand now
    ai = session.pipeline.gpu_crowd.store()
chest = np.stack([ai.x, np.full(ai.n, 1.2), ai.z], axis=1)
camera = session.pipeline.camera
ahead = (chest - camera.eye) @ (np.asarray(camera.target) - camera.eye) > 0  # in front of the camera (the follow camera sees some)
pixels = session.pipeline.project(chest, wnd.buffer_size)
shown = ahead & np.all((pixels > 0) & (pixels < wnd.buffer_size), axis=1)
near = int(np.flatnonzero(shown)[np.argmin(np.linalg.norm(chest[shown] - camera.eye, axis=1))])
x, y = session.pipeline.project(chest[near : near + 1], wnd.buffer_size)[0] / wnd.pixel_ratio
window.on_mouse_press_event(x, y, wnd.mouse.left)
window.on_mouse_release_event(x, y, wnd.mouse.left)
for _ in range(6):  # a crowd on the GPU answers a pick with its facts, N frames later (nothing moves meanwhile)
    if session.selected >= 0:
        break
    render_frame(window, 0.0)
result["selected"], result["nearest"] = session.selected, near
window.on_key_event(wnd.keys.P, wnd.keys.ACTION_PRESS, KeyModifiers())
result["paused"] = session.paused
window.on_key_event(wnd.keys.P, wnd.keys.ACTION_PRESS, KeyModifiers())
window.on_key_event(wnd.keys.P, wnd.keys.ACTION_RELEASE, KeyModifiers())
# The survivor, driven as a player drives it: W held behind it (the follow camera), D to strafe, space to
# swing; the zombies close in and hurt it, and the HUD's health goes down.
survivor = session.pipeline.survivor
result["camera"] = window.camera_mode
render_frame(window, 1 / 30)
result["hud_before"] = dict(window.overlay.hud_shown)
start = survivor.position.copy()
window.on_key_event(wnd.keys.W, wnd.keys.ACTION_PRESS, KeyModifiers())
for _ in range(20):
    render_frame(window, 1 / 30)
result["ran_m"] = float(np.hypot(*(survivor.position - start)))
result["ran_weight"] = float(session.pipeline.processor.read_palette().shape[0] and window.session.pipeline.survivor._weights[1])
window.on_key_event(wnd.keys.W, wnd.keys.ACTION_RELEASE, KeyModifiers())
window.on_key_event(wnd.keys.D, wnd.keys.ACTION_PRESS, KeyModifiers())
for _ in range(10):
    render_frame(window, 1 / 30)
result["strafe_weight"] = float(survivor._weights[2])
window.on_key_event(wnd.keys.D, wnd.keys.ACTION_RELEASE, KeyModifiers())
window.on_key_event(wnd.keys.SPACE, wnd.keys.ACTION_PRESS, KeyModifiers())
window.on_key_event(wnd.keys.SPACE, wnd.keys.ACTION_RELEASE, KeyModifiers())
render_frame(window, 1 / 30)
result["swinging"] = survivor.action == 1
for _ in range(240):  # standing among the horde
    render_frame(window, 1 / 30)
    if window.overlay.hud_shown["health"] < result["hud_before"]["health"]:
        break
result["hud_after"] = dict(window.overlay.hud_shown)
window.on_key_event(wnd.keys.C, wnd.keys.ACTION_PRESS, KeyModifiers())
result["camera_after_c"] = window.camera_mode
# V: the horizon view (the fog thinned to the crowd's far side on the plane), and back.
window.on_key_event(wnd.keys.V, wnd.keys.ACTION_PRESS, KeyModifiers())
window.on_key_event(wnd.keys.V, wnd.keys.ACTION_RELEASE, KeyModifiers())
render_frame(window, 1 / 30)
camera = window.session.pipeline.camera
result["horizon"] = {"eye_y": float(camera.eye[1]), "far": float(camera.far), "stats_drawn": window.session.pipeline.renderer.last["visible"]}
window.on_key_event(wnd.keys.V, wnd.keys.ACTION_PRESS, KeyModifiers())
render_frame(window, 1 / 30)
result["after_horizon"] = {"eye_y": float(camera.eye[1]), "fog_reach": camera.fog_reach}
result["gl"] = window.ctx.info["GL_RENDERER"]
window.release()
window.wnd.destroy()
print(json.dumps(result))
