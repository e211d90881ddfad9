"""The ImGui panel: frame rate, pass timings and every animation control. Thin: each widget calls one
``apply`` action, and each action is one CrowdSession method (so tests drive the same path without a
window). A control given a bad value shows its one-line error in the panel and changes nothing.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from crowd.errors import CrowdError
from crowd.timing import SampleRing
from crowd.session import CrowdSession
from crowd.settings import SETTINGS, SOURCE_RATE
from crowd.stats import weapon_stats

# Widget ranges and choices come from the settings schema, where each setting's bounds are declared.
AGENTS, TIME_SCALE, CROSSFADE = SETTINGS["agents"], SETTINGS["time_scale"], SETTINGS["crossfade"]
CLIP_SPEED, WEIGHT, BAKE_FPS = SETTINGS["clip_speed"], SETTINGS["layer_weight"], SETTINGS["bake_fps"]
LOD, LATENCY = SETTINGS["lod_distances"], SETTINGS["readback_latency"]
LOD_FADE, IMPOSTOR_DISTANCE, IMPOSTOR_MODES = SETTINGS["lod_fade"], SETTINGS["impostor_distance"], SETTINGS["impostors"].choices
LOD_ERROR = SETTINGS["lod_error_px"]
PRECISIONS, INTERPOLATIONS = SETTINGS["precision"].choices, SETTINGS["interpolation"].choices
BOUND, MORPH_WEIGHT = SETTINGS["compression_bound_mm"], SETTINGS["morph_weight"]
CULL_PATHS = SETTINGS["cull"].choices

HISTORY_SECONDS = 5.0
REFRESH_SECONDS = 0.25  # how often the pass medians are worked out again
PLOT_HEIGHT = 90.0  # pixels: with the default sections open the panel fits a 720-pixel window unscrolled
LAYER_NAMES = ("idle", "walk", "run", "action")
# The panel's width: this share of the display's, within these pixels; it keeps MARGIN pixels from the edges.
PANEL_WIDTH_SHARE, PANEL_WIDTH_MIN, PANEL_WIDTH_MAX, MARGIN = 0.3, 360.0, 560.0, 10.0
# The labels drawn right of sliders and combos (the longest decides how wide they are).
LABELS = ("agents", "agents (any)", "time scale", "seed", "cross-fade (s)", "character", "speed", "precision", "bound (mm)",
          "interpolation", "LOD distances (m)", "LOD fade (m)", "impostors", "impostor distance (m)", "cull path", "read-back lag",
          "bake fps") + LAYER_NAMES
SECTIONS = ("Frame", "Crowd", "Clips", "Layer weights", "Morph targets", "Bake and rendering", "Selected agent", "Keys")
OPEN_AT_START = ("Frame", "Crowd")  # with these open the panel fits a 720-pixel window; the others fold
KEYS = ("W/A/S/D: run (strafe with A and D)", "right click: run there", "space: swing", "C: follow or orbit camera",
        "drag: turn the camera", "wheel: zoom", "left click: select a zombie", "P: pause", ".: one step", "H: hide this panel")


class Panel:
    def __init__(self, session: CrowdSession, scene_path: Path | None):
        self.session = session
        self.scene_path = scene_path or Path("out/scene.toml")
        self.status = ""
        self.frame_times = SampleRing(2000)  # seconds; the plot shows the last HISTORY_SECONDS of them
        self.visible = True
        bake = session.pipeline.bake
        self._source_rate = bake.fps == SOURCE_RATE
        self._bake_fps = BAKE_FPS.default if self._source_rate else float(bake.fps)
        self._precision, self._interpolation = bake.precision, session.pipeline.processor.interpolation
        self._bound_mm = bake.bound_mm
        self._seed = session.pipeline.config.seed
        self._held = {layer: [False, 1.0] for layer in range(4)}
        self._weights_selected_only = False
        self._morphs_selected_only = False
        self._morph_values: dict[str, float] = {}  # each target's slider, held or not
        self._character = 0  # whose clips the clip section shows (the selected agent's, once one is picked)
        self._selected = -1
        self._opened_for = -1  # the selection the inspector's section was last opened for
        self._to_open: set[str] = set()
        self._passes: list[tuple[str, str, float]] = []  # (pass, clock, median ms), as last worked out
        self._passes_at = -math.inf
        self._frame_text, self._frame_text_at, self._plotted = "", -math.inf, 1

    # -- actions: the only way the panel changes anything

    ACTIONS = {
        "pause": "set_paused", "step": "step_once", "clip_speed": "set_clip_speed", "clip_loop": "set_clip_loop",
        "play": "play", "weight": "set_weight", "rebake": "start_rebake", "measure_error": "measure_error", "morph": "set_morph_weight",
    }

    def apply(self, action: str, *args, **kwargs) -> bool:
        """Run one control's action (a setting's name sets it through the session's one path); False (and
        the reason in the status line) when it was refused."""
        try:
            if action == "save":
                backup = self.session.save(self.scene_path)
                self.status = f"saved {self.scene_path}" + (f" (previous kept as {backup.name})" if backup else "")
            elif action in self.ACTIONS:
                getattr(self.session, self.ACTIONS[action])(*args, **kwargs)
                self.status = ""
            else:
                self.session.set(action, *args)
                self.status = ""
            return True
        except (CrowdError, OSError) as exc:
            self.status = str(exc).splitlines()[0]
            return False

    # -- drawing

    def record_frame(self, seconds: float) -> None:
        self.frame_times.append(float(seconds))

    def draw(self) -> None:
        from imgui_bundle import imgui

        # A re-bake's thread done: its bake is in use from this frame (hidden or folded, the panel still polls).
        failed = self.session.poll_rebake()
        if failed is not None:
            self.status = failed
        if not self.visible:
            return
        # Sized by the display, every frame: a fixed width (a share of the display's, clamped), and as tall
        # as its open sections up to the display's height (then it scrolls). Text wraps at that width.
        display = imgui.get_io().display_size
        width = min(max(display.x * PANEL_WIDTH_SHARE, PANEL_WIDTH_MIN), PANEL_WIDTH_MAX, max(display.x - 2 * MARGIN, 1.0))
        imgui.set_next_window_pos(imgui.ImVec2(MARGIN, MARGIN), imgui.Cond_.first_use_ever)
        imgui.set_next_window_size_constraints(imgui.ImVec2(width, 0), imgui.ImVec2(width, max(display.y - 2 * MARGIN, 1.0)))
        imgui.begin("crowd", None, imgui.WindowFlags_.always_auto_resize)
        # Every slider and combo leaves room for the longest label on its right.
        imgui.push_item_width(-(max(imgui.calc_text_size(label).x for label in LABELS) + imgui.get_style().item_inner_spacing.x))
        if self.session.selected != self._opened_for:  # a new selection opens its section
            self._opened_for = self.session.selected
            if self.session.selected >= 0:
                self.open_sections("Selected agent")
        for name, draw in zip(SECTIONS, (self._draw_timing, self._draw_crowd, self._draw_clips, self._draw_weights, self._draw_morphs,
                                         self._draw_rendering, self._draw_inspector, self._draw_keys)):
            if name in self._to_open:
                self._to_open.discard(name)
                imgui.set_next_item_open(True)
            if imgui.collapsing_header(name, imgui.TreeNodeFlags_.default_open if name in OPEN_AT_START else 0):
                draw(imgui)
        imgui.separator()
        if imgui.button("Save scene"):
            self.apply("save")
        imgui.same_line()
        imgui.text_wrapped(str(self.scene_path))
        if self.session.rebake_progress is not None:
            imgui.text_wrapped(self.session.rebake_progress)
        if self.status:
            imgui.push_style_color(imgui.Col_.text, imgui.ImVec4(1.0, 0.6, 0.3, 1.0))
            imgui.text_wrapped(self.status)
            imgui.pop_style_color()
        imgui.pop_item_width()
        imgui.end()

    def open_sections(self, *names: str) -> None:
        """Unfold these sections at the next frame (a new selection opens its own; the tests open them all)."""
        self._to_open.update(names)

    def _draw_keys(self, imgui) -> None:
        for line in KEYS:
            imgui.text_wrapped(line)

    def _draw_timing(self, imgui) -> None:
        from imgui_bundle import implot

        times = self.frame_times
        if len(times):
            now = time.perf_counter()
            if now - self._frame_text_at >= REFRESH_SECONDS:  # (as the passes' medians below: a few times a second)
                typical = float(np.median(times.recent(60)))
                self._frame_text = f"{1.0 / max(typical, 1e-6):.0f} fps   frame {typical * 1e3:.2f} ms (median of 60)"
                self._plotted = int(min(len(times), max(1, HISTORY_SECONDS / max(typical, 1e-4))))
                self._frame_text_at = now
            recent = times.recent(self._plotted)[::-1]
            imgui.text_wrapped(self._frame_text)
            if implot.begin_plot("##frame time", imgui.ImVec2(-1, PLOT_HEIGHT), implot.Flags_.no_legend | implot.Flags_.no_mouse_text):
                implot.setup_axes("", "ms", implot.AxisFlags_.no_tick_labels, implot.AxisFlags_.auto_fit)
                implot.setup_axis_limits(implot.ImAxis_.x1, 0, len(recent), implot.Cond_.always)
                implot.plot_line("ms", np.ascontiguousarray(recent * 1e3))
                implot.end_plot()
        # The passes' medians in two pairs of columns, so the section stays short. Worked out a few times
        # a second, not every frame: a figure that changes every frame cannot be read, and 15 medians a
        # frame were a third of the panel's CPU time.
        now = time.perf_counter()
        if now - self._passes_at >= REFRESH_SECONDS:
            timer = self.session.pipeline.timer
            self._passes = [(name, timer.clock[name], float(np.median(samples))) for name in timer.order
                            if len(samples := timer.recent(name, 60))]
            self._passes_at = now
        shown = self._passes
        if shown and imgui.begin_table("passes", 4, imgui.TableFlags_.sizing_stretch_prop):
            for k, (name, clock, ms) in enumerate(shown):
                if k % 2 == 0:
                    imgui.table_next_row()
                imgui.table_next_column()
                imgui.text(name)
                imgui.table_next_column()
                imgui.text(f"{ms:.3f} {clock.upper()}")
            imgui.end_table()

    def _draw_crowd(self, imgui) -> None:
        s = self.session
        changed, agents = imgui.slider_int("agents", s.pipeline.agents, *AGENTS.slider)
        if changed:
            self.apply("agents", agents)
        changed, agents = imgui.input_int("agents (any)", s.pipeline.agents, 100, 1000)
        if changed:
            self.apply("agents", min(max(int(AGENTS.low), agents), int(AGENTS.high)))
        changed, paused = imgui.checkbox("pause", s.paused)
        if changed:
            self.apply("pause", paused)
        imgui.same_line()
        if imgui.button("step"):
            self.apply("step")
        changed, scale = imgui.slider_float("time scale", s.time_scale, *TIME_SCALE.slider)
        if changed:
            self.apply("time_scale", scale)
        if imgui.button("new crowd"):
            self.apply("seed", self._seed)
        imgui.same_line()
        imgui.set_next_item_width(imgui.get_content_region_avail().x - imgui.calc_text_size("seed").x - imgui.get_style().item_inner_spacing.x)
        _, self._seed = imgui.input_int("seed", self._seed)
        changed, fade = imgui.slider_float("cross-fade (s)", s.ai_setting("crossfade"), *CROSSFADE.slider)
        if changed:
            self.apply("crossfade", fade)
        counts = s.pipeline.crowd_ai.counts()  # (a crowd on the GPU: its facts, N frames late)
        p = s.pipeline
        imgui.text_wrapped(f"AI on the {p.ai_path.upper()}" + (f" ({p.ai_note})" if p.ai_note else ""))
        if imgui.begin_table("states", 3):
            for name, count in counts.items():
                imgui.table_next_column()
                imgui.text(f"{name} {count:,}")
            imgui.end_table()
        if len(s.pipeline.cast) > 1:
            imgui.text_wrapped("cast: " + ", ".join(f"{m.name} {n:,}" for m, n in zip(s.pipeline.cast, s.pipeline.ai.cast)))

    def _draw_clips(self, imgui) -> None:
        s = self.session
        cast = s.pipeline.cast
        if s.selected != self._selected:  # a new selection shows its own character's clips
            self._selected = s.selected
            if 0 <= s.selected < s.pipeline.agents:
                self._character = s.character_of(s.selected)
        self._character = min(self._character, len(cast) - 1)
        if len(cast) > 1:
            _, self._character = imgui.combo("character", self._character, [m.name for m in cast])
        member = cast[self._character]
        k = self._character
        for i, clip in enumerate(member.bake.clips):
            imgui.push_id(f"clip{k}_{i}")
            roles = [r for r, name in member.roles.items() if name == clip.name]
            imgui.text_wrapped(f"{clip.name} ({', '.join(roles) or '-'}, {clip.duration:.2f} s)")
            changed, speed = imgui.slider_float("speed", member.clip_speed.get(clip.name, 1.0), *CLIP_SPEED.slider)
            if changed:
                self.apply("clip_speed", clip.name, speed, character=k)
            imgui.same_line()
            changed, loop = imgui.checkbox("loop", clip.loop)
            if changed:
                self.apply("clip_loop", clip.name, loop, character=k)
            if imgui.button("play on selected"):
                self.apply("play", clip.name, selected_only=True, character=k)
            imgui.same_line()
            if imgui.button("play on all"):
                self.apply("play", clip.name, selected_only=False, character=k)
            imgui.pop_id()
        if s.forced is not None and imgui.button("back to the AI"):
            self.apply("play", None)

    def _draw_weights(self, imgui) -> None:
        _, self._weights_selected_only = imgui.checkbox("selected agent only", self._weights_selected_only)
        for layer, name in enumerate(LAYER_NAMES):
            imgui.push_id(f"w{layer}")
            held, value = self._held[layer]
            changed_h, held = imgui.checkbox("hold", held)
            imgui.same_line()
            changed_v, value = imgui.slider_float(name, value, *WEIGHT.slider)
            if changed_h or (held and changed_v):
                if self.apply("weight", layer, value if held else None, selected_only=self._weights_selected_only):
                    self._held[layer] = [held, value]
            else:
                self._held[layer][1] = value
            imgui.pop_id()

    def _draw_morphs(self, imgui) -> None:
        """A slider per morph target of the selected agent's character (else the first whose targets move):
        held, its weight replaces what the clips and the agent's variation give, on that agent or on all."""
        k = self.session.morph_character()
        if k is None:
            imgui.text_wrapped("No character moves morph targets in this scene (the morphs setting is off, or no clip or "
                               "variation moves one).")
            return
        member = self.session.pipeline.cast[k]
        imgui.text_wrapped(f"{member.name}: a held weight replaces the clips' and the variation's.")
        _, self._morphs_selected_only = imgui.checkbox("selected agent only##morphs", self._morphs_selected_only)
        held = self.session.held_morphs()
        for name in member.character.morphs:
            imgui.push_id(f"morph {name}")
            imgui.text_wrapped(name)
            value = self._morph_values.get(name, held.get(name, 0.0))
            changed_h, on = imgui.checkbox("hold", name in held)
            imgui.same_line()
            changed_v, value = imgui.slider_float("##weight", value, *MORPH_WEIGHT.slider)
            self._morph_values[name] = value
            if changed_h or (on and changed_v):
                self.apply("morph", name, value if on else None, selected_only=self._morphs_selected_only)
            imgui.pop_id()

    def _draw_rendering(self, imgui) -> None:
        s = self.session
        p = s.pipeline
        _, self._source_rate = imgui.checkbox("source rate (each clip at its own key rate)", self._source_rate)
        if not self._source_rate:
            _, self._bake_fps = imgui.slider_float("bake fps", self._bake_fps, *BAKE_FPS.slider, "%.0f")
        _, index = imgui.combo("precision", PRECISIONS.index(self._precision), list(PRECISIONS))
        self._precision = PRECISIONS[index]
        if self._precision == "compressed":
            _, self._bound_mm = imgui.slider_float("bound (mm)", self._bound_mm, *BOUND.slider, "%.3f", imgui.SliderFlags_.logarithmic)
        _, index = imgui.combo("interpolation", INTERPOLATIONS.index(self._interpolation), list(INTERPOLATIONS))
        self._interpolation = INTERPOLATIONS[index]
        if self.session.rebake_progress is None and imgui.button("re-bake"):  # while one is under way its line shows at the panel's foot
            self.apply("rebake", SOURCE_RATE if self._source_rate else round(self._bake_fps), self._precision, self._interpolation,
                       self._bound_mm)
        imgui.same_line()
        if imgui.button("measure error"):
            self.apply("measure_error")
        rate = "source rate" if p.bake.fps == SOURCE_RATE else f"{p.bake.fps:g} fps"
        clips, size = sum(len(m.bake.clips) for m in p.cast), sum(m.bake.nbytes for m in p.cast)
        imgui.text_wrapped(f"baked: {clips} clips at {rate}, {p.bake.precision}, {p.processor.interpolation}, {size:,} bytes")
        if p.bake.compression is not None:
            c = p.bake.compression
            imgui.text_wrapped(f"compressed {c['ratio']:.2f}:1 against f32, keys within {c['max_key_error_mm']:.3g} mm (bound {c['bound_mm']:g} mm)")
        if s.bake_error is not None:
            e = s.bake_error
            imgui.text_wrapped(f"shell error against float64: max {e['max_error_mm']:.3g} mm, p99 {e['p99_error_mm']:.3g} mm "
                       f"({e['poses']} poses, GPU)")
        changed, distances = imgui.drag_float3("LOD distances (m)", list(p.renderer.lod_distances), 0.5, *LOD.slider)
        if changed:
            self.apply("lod_distances", tuple(map(float, np.maximum.accumulate(distances))))  # dragging one past the next pushes the next along
        if any(m.character.lod_distances for m in p.cast):  # only a character with generated LODs reads it
            changed, pixels = imgui.slider_float("LOD error (px)", float(p.config.lod_error_px), *LOD_ERROR.slider, "%.2f")
            if changed:
                self.apply("lod_error_px", max(float(pixels), LOD_ERROR.slider[0]))
        changed, fade = imgui.slider_float("LOD fade (m)", float(p.config.lod_fade), *LOD_FADE.slider, "%.1f")
        if changed:
            self.apply("lod_fade", float(fade))
        changed, index = imgui.combo("impostors", IMPOSTOR_MODES.index(p.config.impostors), list(IMPOSTOR_MODES))
        if changed:
            self.apply("impostors", IMPOSTOR_MODES[index])
        changed, metres = imgui.drag_float("impostor distance (m)", float(p.config.impostor_distance), 0.5, *IMPOSTOR_DISTANCE.slider, "%.1f")
        if changed:
            self.apply("impostor_distance", max(float(metres), IMPOSTOR_DISTANCE.slider[0]))
        atlas_mb = p.renderer.gpu_bytes()["impostors"] / 1e6
        imgui.text_wrapped(f"impostor atlases {atlas_mb:.1f} MB" if atlas_mb else "no impostors (meshes only)")
        changed, on = imgui.checkbox("culling", p.renderer.culling)
        if changed:
            self.apply("culling", on)
        imgui.same_line()
        changed, on = imgui.checkbox("occlusion", p.config.occlusion)
        if changed:
            self.apply("occlusion", on)
        changed, index = imgui.combo("cull path", CULL_PATHS.index(p.config.cull), list(CULL_PATHS))
        if changed:
            self.apply("cull", CULL_PATHS[index])
        imgui.text_wrapped(f"culled on the {p.renderer.cull_path.upper()}" if p.renderer.culling else "no culling")
        changed, on = imgui.checkbox("shadows", p.renderer.shadows)
        if changed:
            self.apply("shadows", on)
        changed, on = imgui.checkbox("weapons", p.config.weapons)
        if changed:
            self.apply("weapons", on)
        imgui.same_line()
        changed, on = imgui.checkbox("foot lock", p.config.foot_lock)
        if changed:
            self.apply("foot_lock", on)
        imgui.same_line()
        changed, on = imgui.checkbox("morph targets", p.config.morphs)
        if changed:
            self.apply("morphs", on)
        lock = p.foot_lock_state()
        if not lock["on"] and p.config.foot_lock:
            imgui.text_wrapped(f"foot lock off: {lock['why']}")
        changed, latency = imgui.slider_int("read-back lag", p.latency, *LATENCY.slider, "%d frames")
        if changed:
            self.apply("readback_latency", latency)
        if p.weapons is not None:
            w = weapon_stats(p)
            imgui.text_wrapped(f"{w['drawn']} weapons, pose lag {w['pose_lag_ms']:.1f} ms ({w['latency_frames']} frames x frame time), {w['stalls']} stalls")
        imgui.text_wrapped("skinning: dual quaternions (linear blend skinning is not built)")
        last = p.renderer.last
        imgui.text_wrapped(f"{last['instances']:,} instances, {last['triangles']:,} triangles, LODs {last['lod_counts']}")

    def _draw_inspector(self, imgui) -> None:
        info = self.session.inspect()
        if info is None:
            imgui.text_wrapped("click a zombie to select it")
            return
        imgui.text_wrapped(f"agent {info['agent']} ({info['character']}): {info['state']}, health {info['health']}, {info['speed']:.2f} m/s")
        imgui.text_wrapped(f"phase {info['phase']:.3f}, weapon {info['weapon'] or 'none'}")
        for name, layer in zip(LAYER_NAMES, info["layers"]):
            imgui.text_wrapped(f"{name}: {layer['clip']}, phase {layer['phase']:.3f} weight {layer['weight']:.3f}"
                       + (f" mask {layer['mask']}" if layer["mask"] >= 0 else ""))
