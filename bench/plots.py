"""Report plots, drawn with imgui-bundle's implot into an offscreen framebuffer (EGL) and saved as PNG,
so a plot in the docs is the same widget the demo's panel uses, with no plotting library added."""

from __future__ import annotations

from pathlib import Path

import numpy as np

COLORS = {"dq_lerp": (0.85, 0.33, 0.10, 1.0), "qt_lerp": (0.00, 0.45, 0.74, 1.0), "qt_corrected": (0.49, 0.18, 0.56, 1.0),
          "qt_cubic": (0.47, 0.67, 0.19, 1.0)}
FRONT_COLOR = (0.10, 0.10, 0.10, 1.0)


def _render(size: tuple[int, int], draw) -> np.ndarray:
    """One ImGui frame of `draw(imgui, implot)` filling a window of `size`, as an RGB image."""
    import imgui_bundle
    from imgui_bundle import imgui, implot
    from crowd.gl import Offscreen, headless_context, import_moderngl_window

    import_moderngl_window()
    from moderngl_window.integrations.imgui_bundle import ModernGLRenderer

    ctx = headless_context()
    gui = imgui.create_context()
    plot = implot.create_context()
    renderer = target = None
    try:
        io = imgui.get_io()
        io.set_ini_filename("")  # no imgui.ini next to the caller
        io.display_size = imgui.ImVec2(*size)
        font = Path(imgui_bundle.__file__).parent / "assets" / "fonts" / "DroidSans.ttf"
        if font.exists():
            io.fonts.add_font_from_file_ttf(str(font), 19.0)
        imgui.style_colors_light()
        implot.style_colors_light()
        renderer = ModernGLRenderer(ctx=ctx, display_size=size)
        target = Offscreen(ctx, size)
        for _ in range(2):  # the first frame lays out the legend and the tick labels
            imgui.new_frame()
            imgui.set_next_window_pos(imgui.ImVec2(0, 0))
            imgui.set_next_window_size(imgui.ImVec2(*size))
            imgui.begin("plot", flags=imgui.WindowFlags_.no_decoration | imgui.WindowFlags_.no_move)
            draw(imgui, implot)
            imgui.end()
            imgui.render()
            target.framebuffer.use()
            target.framebuffer.clear(1.0, 1.0, 1.0, 1.0)
            renderer.render(imgui.get_draw_data())
        return target.image()
    finally:
        if renderer is not None:
            renderer.shutdown()
        if target is not None:
            target.release()
        implot.destroy_context(plot)
        imgui.destroy_context(gui)
        ctx.release()


def _log_ticks(lo: float, hi: float) -> list[float]:
    """Round values (1, 1.2, 1.5, 2, 3, 4, 5, 6, 8 times powers of 10) between lo and hi."""
    out = []
    for e in range(int(np.floor(np.log10(lo))), int(np.ceil(np.log10(hi))) + 1):
        out += [m * 10.0 ** e for m in (1, 1.2, 1.5, 2, 3, 4, 5, 6, 8) if lo <= m * 10.0 ** e <= hi]
    return [float(f"{t:.3g}") for t in out]


def error_plot(report: dict, path: Path, size: tuple[int, int] = (1600, 1000)) -> None:
    """Max shell error (x, log) against processor GPU ms at the larger crowd (y, log; the animation data's
    bytes instead where the report's GPU ms were not measured, as on llvmpipe): one marked point
    per configuration (colour: interpolation, marker: storage, label: bake rate), the Pareto front
    ringed, the default marked, the 1 mm target as a vertical line; the device and versions in the title."""
    from crowd.images import write_png

    rows = report["rows"]
    if not rows:
        raise ValueError("the report has no rows to plot")
    agents = report.get("cost_agents", [10000, 100000])[1]
    err = np.array([r["max_error_mm"] for r in rows], np.float64)
    timed = all(r.get("gpu_ms_100k") for r in rows)  # else (llvmpipe's timer queries answer 0): error against bytes
    ms = np.array([r["gpu_ms_100k"] if timed else r["bytes"] for r in rows], np.float64)
    y_label = (f"animation processor GPU ms, {agents:,} agents (log)" if timed
               else "animation data on the GPU, bytes (log; the GPU ms were not measured on this GL)")
    front = sorted((i for i, r in enumerate(rows) if r.get("pareto")), key=lambda i: err[i])
    default = [i for i, r in enumerate(rows) if r.get("default")]
    title = f"Error against run time: {report.get('device', '?')}"

    def label(r):
        rate = "src" if r["bake_fps"] == "source" else f"{r['bake_fps']:g}"
        return f"{rate} {r['storage']}"

    def draw(imgui, implot):
        if not implot.begin_plot(title, imgui.ImVec2(-1, -1)):
            return
        implot.setup_axes("max shell error, mm (3 cm shell against the float64 reference; log)", y_label)
        implot.setup_axis_scale(implot.ImAxis_.x1, implot.Scale_.log10)
        implot.setup_axis_scale(implot.ImAxis_.y1, implot.Scale_.log10)
        implot.setup_axis_limits(implot.ImAxis_.x1, float(err.min()) / 2.5, float(err.max()) * 2.5, implot.Cond_.always)
        lo, hi = float(ms.min()) / 1.15, float(ms.max()) * 1.15
        implot.setup_axis_limits(implot.ImAxis_.y1, lo, hi, implot.Cond_.always)
        ticks = _log_ticks(lo, hi)  # the ms range is often under a decade: label more than the powers of 10
        implot.setup_axis_ticks(implot.ImAxis_.y1, ticks, [f"{t:g}" for t in ticks], False)
        implot.setup_legend(implot.Location_.north_west)
        target = float(report.get("target_mm", 1.0))
        implot.set_next_line_style(imgui.ImVec4(0.6, 0.0, 0.0, 1.0), 2.0)
        implot.plot_inf_lines(f"{target:g} mm target", np.array([target]))
        for interp, color in COLORS.items():
            storages = sorted({r["storage"] for r in rows if r["interpolation"] == interp})
            markers = {"f32": implot.Marker_.circle, "f16": implot.Marker_.square}  # compressed bakes (one per bound): triangles
            for storage in storages:
                marker = markers.get(storage, implot.Marker_.up)
                idx = [i for i, r in enumerate(rows) if r["interpolation"] == interp and r["storage"] == storage]
                if not idx:
                    continue
                implot.set_next_marker_style(marker, 8.0, imgui.ImVec4(*color), 1.0, imgui.ImVec4(*color))
                implot.plot_scatter(f"{interp}, {storage}", np.ascontiguousarray(err[idx]), np.ascontiguousarray(ms[idx]))
        if front:  # the front is over error, ms and bytes, so it is ringed, not drawn as a line
            implot.set_next_marker_style(implot.Marker_.circle, 13.0, imgui.ImVec4(0, 0, 0, 0), 2.0, imgui.ImVec4(*FRONT_COLOR))
            implot.plot_scatter("Pareto front (error, ms, bytes)", np.ascontiguousarray(err[front]), np.ascontiguousarray(ms[front]))
        if default:
            implot.set_next_marker_style(implot.Marker_.diamond, 22.0, imgui.ImVec4(0, 0, 0, 0), 3.0, imgui.ImVec4(0.8, 0.0, 0.0, 1.0))
            implot.plot_scatter("default", np.ascontiguousarray(err[default]), np.ascontiguousarray(ms[default]))
        for i, r in enumerate(rows):  # "source" labels go below the point: they often share it with a fixed rate
            implot.plot_text(label(r), float(err[i]), float(ms[i]), imgui.ImVec2(0, 16 if r["bake_fps"] == "source" else -16))
        implot.end_plot()

    write_png(path, _render(size, draw))


PEER_STYLE = {  # (system, mode) → colour, marker
    ("crowd", "walk"): ((0.00, 0.45, 0.74, 1.0), "circle"),
    ("crowd", "blend2"): ((0.30, 0.75, 0.93, 1.0), "square"),
    ("crowd", "walk_lod"): ((0.00, 0.20, 0.45, 1.0), "diamond"),
    ("panda3d", "cpu_walk"): ((0.85, 0.33, 0.10, 1.0), "circle"),
    ("panda3d", "gpu_walk"): ((0.64, 0.08, 0.18, 1.0), "up"),
    ("panda3d", "gpu_blend2"): ((0.93, 0.69, 0.13, 1.0), "square"),
    ("panda3d", "cpu_walk_lod"): ((0.85, 0.33, 0.10, 1.0), "diamond"),
    ("panda3d", "gpu_walk_lod"): ((0.64, 0.08, 0.18, 1.0), "diamond"),
    ("panda3d", "gpu_walk_threaded"): ((0.49, 0.18, 0.56, 1.0), "right"),
}


def peers_plot(report: dict, path: Path, size: tuple[int, int] = (1600, 1000)) -> None:
    """Median frame ms (y, log) against agents (x, log) for every (system, mode) of a ``crowd-bench
    peers`` report, with the 16.7 and 33.3 ms budgets as horizontal lines."""
    from crowd.images import write_png

    series: dict = {}
    for r in report["rows"]:
        series.setdefault((r["system"], r["mode"]), []).append((r["agents"], r["frame_ms"]))
    if not series:
        raise ValueError("the report has no rows to plot")
    agents = np.array([a for s in series.values() for a, _ in s], np.float64)
    ms = np.array([m for s in series.values() for _, m in s], np.float64)
    gls = sorted({r["info"]["gl"].split(",")[0] for r in report.get("results", []) if r.get("info")})
    title = (f"crowd against Panda3D Actors, frame ms against agents, {report['size'][0]}x{report['size'][1]}, "
             f"{report.get('model', '?')}: {' / '.join(gls) or '?'}")  # the full device string is in the JSON

    def draw(imgui, implot):
        if not implot.begin_plot(title, imgui.ImVec2(-1, -1)):
            return
        implot.setup_axes("agents (log)", "median frame ms, to glFinish (log)")
        implot.setup_axis_scale(implot.ImAxis_.x1, implot.Scale_.log10)
        implot.setup_axis_scale(implot.ImAxis_.y1, implot.Scale_.log10)
        implot.setup_axis_limits(implot.ImAxis_.x1, float(agents.min()) / 1.3, float(agents.max()) * 1.3, implot.Cond_.always)
        implot.setup_axis_limits(implot.ImAxis_.y1, float(ms.min()) / 1.3, float(ms.max()) * 1.3, implot.Cond_.always)
        implot.setup_legend(implot.Location_.north_west)
        for budget in (1000.0 / 60.0, 1000.0 / 30.0):
            implot.set_next_line_style(imgui.ImVec4(0.5, 0.5, 0.5, 1.0), 1.5)
            implot.plot_inf_lines(f"{budget:.1f} ms", np.array([budget]), flags=implot.InfLinesFlags_.horizontal)
        for key, points in series.items():
            points = sorted(points)
            color, marker = PEER_STYLE.get(key, ((0.3, 0.3, 0.3, 1.0), "circle"))
            implot.set_next_line_style(imgui.ImVec4(*color), 2.5)
            implot.set_next_marker_style(getattr(implot.Marker_, marker), 7.0, imgui.ImVec4(*color), 1.0, imgui.ImVec4(*color))
            implot.plot_line(f"{key[0]} {key[1]}", np.array([a for a, _ in points], np.float64), np.array([m for _, m in points], np.float64))
        implot.end_plot()

    write_png(path, _render(size, draw))
