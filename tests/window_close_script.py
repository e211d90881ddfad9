"""Run by tests/test_window.py with DISPLAY on an Xvfb server: the interactive loop (no --frames), which
the user ends by closing the window after three frames. Prints one JSON line of the stats it wrote."""

import json
import sys
from pathlib import Path

import app.window as window_module
from crowd.scene import Scene
from crowd.sim.config import AIConfig

frames = {"n": 0}
render_frame = window_module.render_frame


def render_then_close(window, dt=None):
    render_frame(window, dt)
    frames["n"] += 1
    if frames["n"] == 3:
        window.wnd._window.dispatch_event("on_close")  # what pyglet does when the user closes the window


window_module.render_frame = render_then_close
stats_path = Path(sys.argv[1]) / "stats.json"
# Occlusion on: its depth pyramid copies the window's own framebuffer, which lists no attachments.
stats = window_module.run_window(Scene(agents=30, occlusion=True, ai=AIConfig(half_extent=9.0)), (400, 300), None, None, stats_path, None)
print(json.dumps({"frames": stats["window"]["frames"], "nan": stats["nan_count"], "written": stats_path.exists(),
                  "markers_bytes": stats["gpu_bytes"]["markers"], "hiz": "hiz" in stats["passes_run"],
                  "visible": stats["last_frame"]["visible"]}))
