"""The game's heads-up display: the survivor's health, kills, the zombies near it, and the round's time
against the best so far, in a small undecorated ImGui window at the top right. Thin: it draws what
``CrowdSession.hud()`` says."""

from __future__ import annotations


def draw_hud(imgui, hud: dict | None, width: float) -> dict | None:
    """Draw the HUD of `hud` (nothing without a survivor) at the top right of a `width`-pixel window.
    Returns what it showed (the window test reads it)."""
    if hud is None:
        return None
    imgui.set_next_window_pos(imgui.ImVec2(width - 10, 10), imgui.Cond_.always, imgui.ImVec2(1.0, 0.0))
    flags = (imgui.WindowFlags_.no_decoration | imgui.WindowFlags_.always_auto_resize | imgui.WindowFlags_.no_saved_settings
             | imgui.WindowFlags_.no_focus_on_appearing | imgui.WindowFlags_.no_nav | imgui.WindowFlags_.no_move)
    imgui.set_next_window_bg_alpha(0.6)
    imgui.begin("survivor", None, flags)
    share = hud["health"] / max(hud["health_max"], 1)
    color = imgui.ImVec4(0.85 * (1 - share) + 0.15, 0.75 * share + 0.1, 0.15, 1.0)
    imgui.push_style_color(imgui.Col_.plot_histogram, color)
    imgui.progress_bar(share, imgui.ImVec2(240, 0), f"health {hud['health']}")
    imgui.pop_style_color()
    imgui.text(f"kills {hud['kills']}    zombies near {hud['near']}")
    imgui.text(f"round {hud['round']}: {hud['time_s']:.1f} s    best {hud['best_s']:.1f} s")
    imgui.end()
    return dict(hud)
