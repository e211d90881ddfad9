"""The real window under Xvfb (skipped where Xvfb is absent): it opens, renders the crowd and the panel,
takes a clip setting through the panel, and its screenshot shows both the zombies and the panel."""

from __future__ import annotations

import ctypes.util
import json
import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest
from PIL import Image

from conftest import ROOT


@pytest.fixture(scope="module")
def display():
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        pytest.skip("Xvfb is not installed")
    if ctypes.util.find_library("GL") is None:
        pytest.skip("no libGL (GLX) for a window")
    for number in range(91, 120):
        if not os.path.exists(f"/tmp/.X11-unix/X{number}") and not os.path.exists(f"/tmp/.X{number}-lock"):
            break
    server = subprocess.Popen([xvfb, f":{number}", "-screen", "0", "1024x768x24", "-nolisten", "tcp"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    for _ in range(100):
        if os.path.exists(f"/tmp/.X11-unix/X{number}"):
            break
        time.sleep(0.05)
    yield f":{number}"
    server.terminate()
    server.wait(timeout=10)


def test_window_renders_zombies_and_the_panel_and_takes_clip_settings(display, tmp_path):
    env = {**os.environ, "DISPLAY": display, "XDG_CONFIG_HOME": str(tmp_path / "config")}  # the panel's layout: not the user's
    out = subprocess.run([sys.executable, str(ROOT / "tests" / "window_script.py"), str(tmp_path)], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    # Quiet: no third-party INFO lines (moderngl-window logs its context at INFO) and no warnings.
    assert " - INFO - " not in out.stderr + out.stdout and "Warning" not in out.stderr, out.stderr[-2000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["speed_ok"] and result["loop_ok"] and result["attack_loops"]
    assert result["clip_speed"] == {"shamble": 1.5}
    assert result["bad_refused"] and "playback speed" in result["status"]  # refused in the panel's status line
    assert result["player_moved"] > 0.1 and result["paused"]  # a right click moved the player; P paused
    assert result["selected"] == result["nearest"]  # a left click on a zombie selected it
    # The survivor: behind it the camera follows; W runs (the run clip), D strafes, space swings; the
    # zombies that reach it take its health, and the HUD shows it; C switches to the orbit camera.
    assert result["camera"] == "follow" and result["camera_after_c"] == "orbit"
    assert result["horizon"]["eye_y"] >= 12.0 and result["horizon"]["stats_drawn"] > 0  # V: high over the horde, which it sees
    assert result["after_horizon"]["fog_reach"] is None and result["after_horizon"]["eye_y"] < result["horizon"]["eye_y"]
    assert result["ran_m"] > 1.0 and result["ran_weight"] > 0.5 and result["strafe_weight"] > 0.5 and result["swinging"]
    assert result["hud_before"]["health"] == 100 and result["hud_after"]["health"] < 100, (result["hud_before"], result["hud_after"])
    with_panel, without_panel, empty = (np.asarray(Image.open(tmp_path / f"{n}.png"), np.int32) for n in ("with_panel", "without_panel", "empty"))
    assert with_panel.shape == (450, 800, 3)
    # The panel: its corner of the screen changes when it is hidden; the far side does not.
    panel_area = np.abs(with_panel[20:400, 20:300] - without_panel[20:400, 20:300]).max(axis=2) > 20
    assert panel_area.mean() > 0.5
    # The zombies: outside the panel, the frame with 60 agents differs from the empty one.
    crowd_area = np.abs(without_panel[:, 420:] - empty[:, 420:]).max(axis=2) > 20
    assert crowd_area.mean() > 0.02


def test_closing_the_window_ends_the_run_with_its_stats(display, tmp_path):
    """The interactive loop, ended by the user closing the window: the stats are still taken and written,
    then everything is released (no traceback). Started from a folder of its own, it leaves no imgui.ini
    there or in the checkout: ImGui's layout goes to the user's configuration folder."""
    work, config = tmp_path / "work", tmp_path / "config"
    work.mkdir()
    before = (ROOT / "imgui.ini").exists()
    env = {**os.environ, "DISPLAY": display, "XDG_CONFIG_HOME": str(config), "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, str(ROOT / "tests" / "window_close_script.py"), str(tmp_path)], cwd=work, env=env,
                         capture_output=True, text=True, timeout=300)
    assert not (work / "imgui.ini").exists() and (ROOT / "imgui.ini").exists() == before
    assert (config / "crowd").is_dir() and {p.name for p in (config / "crowd").iterdir()} <= {"imgui.ini"}
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr[-2000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["frames"] in (3, 4)  # pyglet sets is_closing at the next event poll
    assert result["nan"] == 0 and result["written"] and result["markers_bytes"] > 0
    assert result["hiz"] and result["visible"] > 0  # occlusion culling ran on the window's depth, and left the crowd in view
