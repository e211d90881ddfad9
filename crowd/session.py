"""A running crowd and everything a person can do to it: the one object the window's panel drives.

``CrowdSession(ctx, scene)`` builds the pipeline a scene describes and keeps the run-time state the
panel edits: pause, single step, time scale, the selected agent, clips forced on agents, layer weights
held at a value. Each panel control calls one method here, and each method checks its input and says
what is wrong in one line (SessionError), so the panel, the command line and the tests share one path.
Names follow three.js's AnimationMixer: play (force a clip), cross-fade, weight, time scale.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from pathlib import Path

import moderngl
import numpy as np

from .errors import CrowdError
from .anim.bake import BakeError
from .anim.morph import ALL_HELD
from .anim.processor_inputs import ProcessorError
from .asset.model import cast_weapons
from .draw.render import view_proj
from .frame import CLIP, MASK, PHASE, WEIGHT, ForcedClip, LayerOverrides, cast_firsts
from .gl import GLStage
from .pipeline import CrowdPipeline
from .pipeline_config import PipelineError
from .scene import CameraSetting, Scene, SceneError, save_scene
from .live_settings import BAKE_SETTINGS
from .settings import SETTINGS
from .sim.config import LAYERS, STATE_NAMES, AIError
from .sim.player import HEALTH, PlayerError

STRIKE_REACH = 2.0  # metres from the player
PICK_RADIUS = 0.4  # metres: an agent is a vertical cylinder this wide and 1.9 m tall (times its scale)
PICK_HEIGHT = 1.9


class SessionError(CrowdError, ValueError):
    """A control given a value it cannot take; the message is one line."""


class CrowdSession(GLStage):
    def __init__(self, ctx: moderngl.Context, scene: Scene, aspect: float = 16 / 9, scripted_player: bool = False,
                 pipeline: CrowdPipeline | None = None):
        """`pipeline`: one already built from `scene` (the headless loop's, when it draws the panel): the
        session drives it as it is and leaves its release to its owner."""
        self.pipeline = None  # a failure before it exists releases nothing; after, GLStage releases it
        self._owns_pipeline = pipeline is None
        self._rebake: dict | None = None  # a re-bake under way on its thread (start_rebake)
        self.ctx = ctx
        self.scene = scene
        self.paused = False
        self.time_scale = 1.0
        self._selected = -1
        self._pick = None  # a pick the GPU has yet to answer: (its crowd, the request)
        self.overrides = LayerOverrides()  # clips forced and layer weights held: the frame applies them
        self.bake_error: dict | None = None  # the last measure_error(), until the next re-bake
        self._pending_steps = 0
        if pipeline is not None:
            self.pipeline = pipeline
            self.last = pipeline.last
            return
        config = dataclasses.replace(scene.pipeline_config(), scripted_player=scripted_player)
        self.pipeline = CrowdPipeline(ctx, config)
        try:
            for k, entry in enumerate(scene.characters):
                for name, speed in entry.clip_speed.items():
                    self.pipeline.set_clip_speed(name, speed, k)
                for name, loop in entry.clip_loop.items():
                    self.pipeline.set_clip_loop(name, loop, k)
        except (BakeError, AIError) as exc:
            raise SceneError(f"scene {scene.name!r}: {exc}") from None
        self.pipeline.camera = scene.camera_for(aspect) or self.pipeline.default_camera(aspect)
        self.last = self.pipeline.last  # the last frame's state (its view: where the window draws markers)

    # -- time

    def frame(self, framebuffer, dt: float) -> float:
        """Render one frame; the simulation advances dt x time scale (nothing while paused, except a
        single step asked for). Returns the simulated seconds."""
        if not math.isfinite(dt) or dt < 0:
            raise SessionError(f"frame time must be a finite number >= 0, got {dt!r}")
        sim = 0.0 if self.paused else dt * self.time_scale
        if self.paused and self._pending_steps:
            sim = 1.0 / 60.0
            self._pending_steps -= 1
        self.last = self.pipeline.frame(framebuffer, sim, self.overrides)
        if self._pick is not None:
            crowd, request = self._pick
            agent = crowd.picked(request) if crowd is self.pipeline.gpu_crowd else -1  # (a crowd since replaced: no answer)
            if agent is not None:
                self.selected, self._pick = agent, None
        return sim

    def set_paused(self, paused: bool) -> None:
        self.paused = bool(paused)

    def step_once(self) -> None:
        """While paused: the next frame advances one 1/60 s step."""
        self.paused = True
        self._pending_steps += 1

    # -- every setting by name: the panel, the command line, scripted controls and the tests all come here

    def set(self, name: str, value) -> None:
        """Set one setting of crowd.settings on the running crowd: the session's time scale here, the rest
        through the pipeline's one mechanism (crowd.live_settings), which rebuilds only what the setting
        touches. A refusal is SessionError, one line, and nothing
        changes."""
        if name == "time_scale":
            self.time_scale = SETTINGS["time_scale"].check(value, SessionError)
            return
        if name in BAKE_SETTINGS and self._rebake is not None:
            raise SessionError("a re-bake is under way; wait for it to finish")
        try:
            self.pipeline.set(name, value)
        except CrowdError as exc:
            raise SessionError(str(exc).splitlines()[0]) from None
        if name in BAKE_SETTINGS:
            self.bake_error = None  # (measured for the bake it replaced)
        if name == "agents" and self.selected >= self.pipeline.agents:
            self.selected = -1

    def ai_setting(self, name: str):
        """The current value of one AI setting (the panel's sliders start from it)."""
        return getattr(self.pipeline.config.ai, name)

    # -- clips (each character of the cast has its own; `character` is its index, 0 the first)

    def character_names(self) -> list[str]:
        return [m.name for m in self.pipeline.cast]

    def _member(self, character: int):
        try:
            return self.pipeline.member(character)
        except PipelineError as exc:
            raise SessionError(str(exc)) from None

    def clip_names(self, character: int = 0) -> list[str]:
        return [c.name for c in self._member(character).bake.clips]

    def _clip(self, name: str, character: int = 0) -> int:
        try:
            return self._member(character).bake.clip_index(name)
        except BakeError as exc:
            raise SessionError(str(exc)) from None

    def character_of(self, agent: int) -> int:
        """The cast's index of an agent's character."""
        return int(self.pipeline.ai.kind[agent])

    def set_clip_speed(self, name: str, speed: float, character: int = 0) -> None:
        speed = SETTINGS["clip_speed"].check(speed, SessionError)
        self._member(character)
        try:
            self.pipeline.set_clip_speed(name, speed, character)
        except (AIError, BakeError) as exc:
            raise SessionError(str(exc)) from None

    def set_clip_loop(self, name: str, loop: bool, character: int = 0) -> None:
        loop = SETTINGS["clip_loop"].check(loop, SessionError)
        self._member(character)
        try:
            self.pipeline.set_clip_loop(name, loop, character)
        except BakeError as exc:
            raise SessionError(str(exc)) from None

    def play(self, name: str | None, selected_only: bool = True, character: int = 0) -> None:
        """Force a clip of one character, from its start, on the selected agent (which must be that
        character's) or on every agent of that character; None gives control back to the AI."""
        if name is None:
            self.overrides = dataclasses.replace(self.overrides, forced=None)
            return
        if selected_only and self.selected < 0:
            raise SessionError("no agent selected: click one, or play the clip on all agents")
        clip = self._clip(name, character)
        if selected_only and self.character_of(self.selected) != character:
            raise SessionError(f"the selected agent is a {self.pipeline.cast[self.character_of(self.selected)].name}; "
                               f"{name!r} is a clip of the {self.pipeline.cast[character].name}")
        forced = ForcedClip(clip, self.pipeline.ai.time, np.array([self.selected]) if selected_only else None, int(character))
        self.overrides = dataclasses.replace(self.overrides, forced=forced)

    @property
    def forced(self) -> ForcedClip | None:
        """The clip forced by ``play``, or None while the AI chooses."""
        return self.overrides.forced

    def set_weight(self, layer: int, weight: float | None, selected_only: bool = False) -> None:
        """Hold a layer's weight at a value (None: the AI decides again). Layers: 0 idle, 1 walk, 2 run, 3 action."""
        if isinstance(layer, bool) or not isinstance(layer, numbers.Integral) or not 0 <= layer < LAYERS:
            raise SessionError(f"layer must be a whole number from 0 to {LAYERS - 1}, got {layer!r}")
        layer = int(layer)
        held = dict(self.overrides.held)
        if weight is None:
            held.pop(layer, None)
        else:
            weight = SETTINGS["layer_weight"].check(weight, SessionError)
            if selected_only and self.selected < 0:
                raise SessionError("no agent selected")
            held[layer] = (weight, np.array([self.selected]) if selected_only else None)
        self.overrides = dataclasses.replace(self.overrides, held=held)

    def morph_character(self) -> int | None:
        """The character whose morph weights the panel shows: the selected agent's, else the first whose
        targets move in this scene; None when none does."""
        moving = [k for k, m in enumerate(self.pipeline.cast) if m.bake.morphs is not None and not m.player]
        if self.selected >= 0 and self.character_of(self.selected) in moving:
            return self.character_of(self.selected)
        return moving[0] if moving else None

    def set_morph_weight(self, target: str, weight: float | None, selected_only: bool = False) -> None:
        """Hold a morph target's weight (0 to 1) on the selected agent or on every agent of its character
        (the morph_character's), or let the clips and variation decide it again (None). The character's
        held targets apply to one set of agents: the last one named."""
        k = self.morph_character()
        if k is None:
            raise SessionError("no character moves morph targets in this scene (the morphs setting is off, or its clips and scene move none)")
        member = self.pipeline.cast[k]
        if target not in member.character.morphs:
            raise SessionError(f"the {member.name} has no morph target {target!r}; it has {', '.join(member.character.morphs)}")
        if selected_only and self.selected < 0:
            raise SessionError("no agent selected: click one, or hold the weight on all agents")
        weights, _ = self.pipeline.morph_holds.get(k, (np.full(len(member.character.morphs), -1.0), ALL_HELD))
        weights = weights.copy()
        weights[member.character.morphs.index(target)] = -1.0 if weight is None else SETTINGS["morph_weight"].check(weight, SessionError)
        agent = self.selected - cast_firsts(self.pipeline.ai.cast)[k] if selected_only else ALL_HELD
        if np.all(weights < 0.0):
            self.pipeline.morph_holds.pop(k, None)
        else:
            self.pipeline.morph_holds[k] = (weights, agent)

    def held_morphs(self) -> dict[str, float]:
        """The morph_character's held weights, by target."""
        k = self.morph_character()
        if k is None or k not in self.pipeline.morph_holds:
            return {}
        weights, _ = self.pipeline.morph_holds[k]
        return {name: float(w) for name, w in zip(self.pipeline.cast[k].character.morphs, weights) if w >= 0.0}

    # -- rendering features

    def _bake_settings(self, fps, precision, interpolation, bound_mm):
        fps = SETTINGS["bake_fps"].check(fps, SessionError)
        SETTINGS["precision"].check(precision, SessionError)
        if interpolation is not None:
            SETTINGS["interpolation"].check(interpolation, SessionError)
        if bound_mm is not None:
            bound_mm = SETTINGS["compression_bound_mm"].check(bound_mm, SessionError)
        return fps, precision, interpolation, bound_mm

    def rebake(self, fps: float | str, precision: str, interpolation: str | None = None, bound_mm: float | None = None) -> None:
        """Bake again at another rate ("source": each clip at its own key rate), precision or compression
        bound, or process with another interpolation, now (the caller waits)."""
        fps, precision, interpolation, bound_mm = self._bake_settings(fps, precision, interpolation, bound_mm)
        if self._rebake is not None:
            raise SessionError("a re-bake is under way; wait for it to finish")
        try:
            self.pipeline.rebake(fps, precision, interpolation, bound_mm)
        except BakeError as exc:
            raise SessionError(str(exc)) from None
        self.bake_error = None

    def start_rebake(self, fps: float | str, precision: str, interpolation: str | None = None, bound_mm: float | None = None) -> None:
        """The same re-bake while frames go on (the panel's): the bake runs on a thread (numpy, no GL) and
        reports its progress (``rebake_progress``); ``poll_rebake``, called each frame, hands the finished
        bake to the pipeline, whose new processor is made on this thread (GL objects belong to it)."""
        import threading

        fps, precision, interpolation, bound_mm = self._bake_settings(fps, precision, interpolation, bound_mm)
        if self._rebake is not None:
            raise SessionError("a re-bake is under way; wait for it to finish")
        job = {"progress": (0, 0, "starting the bake"), "bake": None, "error": None, "interpolation": interpolation}

        def work():
            try:
                job["bake"] = self.pipeline.make_bake(fps, precision, bound_mm, report=lambda done, total, what: job.__setitem__("progress", (done, total, what)))
            except BakeError as exc:
                job["error"] = str(exc)
            except Exception as exc:  # a thread's failure must reach the panel as a line, not vanish
                job["error"] = f"the re-bake failed: {type(exc).__name__}: {exc}"

        job["thread"] = threading.Thread(target=work, name="crowd re-bake", daemon=True)
        self._rebake = job
        job["thread"].start()

    @property
    def rebake_progress(self) -> str | None:
        """A line saying how far a re-bake under way has got ("baking clips: 3 of 7"), or None."""
        if self._rebake is None:
            return None
        done, total, what = self._rebake["progress"]
        return f"re-baking: {what}, {done} of {total}" if total else f"re-baking: {what}"

    def poll_rebake(self, wait: bool = False) -> str | None:
        """Finish a re-bake whose thread is done (or, with `wait`, wait for it): its bake replaces the old
        one. Returns its error line, or None (nothing under way, still running, or done)."""
        job = self._rebake
        if job is None:
            return None
        if wait:
            job["thread"].join()
        elif job["thread"].is_alive():
            return None
        self._rebake = None
        if job["error"] is not None:
            return job["error"]
        try:
            self.pipeline.use_bake(job["bake"], job["interpolation"])
        except (BakeError, ProcessorError) as exc:
            return str(exc).splitlines()[0]
        self.bake_error = None
        return None

    def measure_error(self, per_clip: int = 24, blends: int = 240) -> dict:
        """The shell error of the current bake and interpolation on this GPU against the float64
        reference (crowd.anim.accuracy), over the scene's clips alone and in random blends: what the panel
        shows next to the bake settings. A few hundred poses: tens of milliseconds on llvmpipe."""
        from .anim import accuracy

        p = self.pipeline
        errors, poses = [], 0
        for member in p.cast:  # every character's bake; the summary is over all of them
            # The reference plays each clip as the bake does (loop settings changed in the panel included).
            clips = [dataclasses.replace(member.character.clip(c.name), loop=c.loop) for c in member.bake.clips]
            samples = accuracy.draw_samples(clips, np.random.default_rng(0), per_clip, blends)
            truth = accuracy.truth(member.character.skeleton, clips, samples.layers)
            errors.append(accuracy.measure_gpu(self.ctx, member.character.skeleton, member.bake, samples.layers, truth, p.processor.interpolation))
            poses += len(samples.layers)
        self.bake_error = {**accuracy.summarise(np.concatenate([e.ravel() for e in errors])), "poses": int(poses)}
        return self.bake_error

    # -- the agent the panel follows

    @property
    def selected(self) -> int:
        """The agent the panel follows (-1: none); the pipeline copies its row out where the crowd is on the GPU."""
        return self._selected

    @selected.setter
    def selected(self, agent: int) -> None:
        self._selected = int(agent)
        if self.pipeline is not None:
            self.pipeline.selected = self._selected

    def _agent_row(self, a: int) -> dict | None:
        """Agent `a`'s state as the panel and the markers show it: the numpy AI's arrays, or, for a crowd on
        the GPU, the row the facts brought back N frames late (None until they do)."""
        crowd = self.pipeline.gpu_crowd
        if crowd is not None:
            return crowd.agent_row(a)
        ai = self.pipeline.ai
        return {"agent": a, "x": float(ai.x[a]), "z": float(ai.z[a]), "vx": float(ai.vx[a]), "vz": float(ai.vz[a]),
                "phase": float(ai.phase[a]), "scale": float(ai.scale[a]), "state": int(ai.state[a]), "action": int(ai.action[a]),
                "health": int(ai.health[a])}

    # -- the player and picking

    def ray(self, x: float, y: float, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """(origin, unit direction) in world space (float64) through pixel (x, y) from the top-left."""
        camera = self.pipeline.camera
        inv = np.linalg.inv(view_proj(camera).astype(np.float64))
        ndc = np.array([2.0 * x / size[0] - 1.0, 1.0 - 2.0 * y / size[1]])
        near = inv @ np.array([ndc[0], ndc[1], -1.0, 1.0])
        far = inv @ np.array([ndc[0], ndc[1], 1.0, 1.0])
        near, far = near[:3] / near[3], far[:3] / far[3]
        direction = far - near
        return np.asarray(camera.eye, np.float64) + near, direction / np.linalg.norm(direction)

    def pick(self, x: float, y: float, size: tuple[int, int]) -> int | None:
        """Select the agent under pixel (x, y): the nearest whose upright cylinder the ray enters. -1 and
        no selection when the ray misses every agent. A crowd on the GPU answers with the facts read back
        N frames later, nothing waiting for it: None now, and ``selected`` is set when the answer is in."""
        ai = self.pipeline.ai
        self.selected = -1
        self._pick = None
        if not ai.n:
            return -1
        origin, d = self.ray(x, y, size)
        if self.pipeline.gpu_crowd is not None:  # the same test as a GPU pass
            self._pick = (self.pipeline.gpu_crowd, self.pipeline.gpu_crowd.pick(origin, d, PICK_RADIUS, PICK_HEIGHT))
            return None
        # Ray against vertical cylinders: solve in the ground plane, then check the height of the hit.
        ox, oz = origin[0] - ai.x, origin[2] - ai.z
        radius = PICK_RADIUS * ai.scale.astype(np.float64)
        a = d[0] * d[0] + d[2] * d[2]
        b = ox * d[0] + oz * d[2]
        c = ox * ox + oz * oz - radius * radius
        disc = b * b - a * c
        ok = (disc >= 0) & (a > 1e-12)
        t = np.where(ok, (-b - np.sqrt(np.maximum(disc, 0.0))) / max(a, 1e-12), np.inf)
        y_hit = origin[1] + t * d[1]
        ok &= (t > 0) & (y_hit >= 0) & (y_hit <= PICK_HEIGHT * ai.scale)
        if not ok.any():
            return -1
        self.selected = int(np.argmin(np.where(ok, t, np.inf)))
        return self.selected

    def ground_point(self, x: float, y: float, size: tuple[int, int]) -> np.ndarray | None:
        """Where the ray through pixel (x, y) meets the ground (x, z), or None above the horizon."""
        origin, d = self.ray(x, y, size)
        if d[1] >= -1e-9:
            return None
        t = -origin[1] / d[1]
        return np.array([origin[0] + t * d[0], origin[2] + t * d[2]])

    def _point(self, point) -> np.ndarray:
        """A ground point (x, z) kept inside the world, or SessionError."""
        p = np.asarray(point, np.float64).reshape(-1)
        if p.shape != (2,) or not np.all(np.isfinite(p)):
            raise SessionError("the player needs a finite ground point (x, z)")
        ai = self.pipeline.ai
        return np.clip(p, ai.origin - ai.half_extent, ai.origin + ai.half_extent)

    def move_player(self, point) -> None:
        """Put the player (the survivor, where there is one) at a ground point (x, z), kept inside the world."""
        p = self._point(point)
        self.pipeline.ai.player = p
        if self.pipeline.survivor is not None:
            self.pipeline.survivor.position = p.copy()

    def go_to(self, point) -> None:
        """The survivor runs to a ground point (x, z) and stops there; without one, the player is put there."""
        p = self._point(point)
        if self.pipeline.survivor is None:
            self.pipeline.ai.player = p
            return
        self.pipeline.survivor.walk_to(p)

    def steer(self, move, face=None) -> None:
        """The survivor moves in a world direction (x, z; its length, at most 1, is the share of full
        speed) facing `face` (x, z), or where it moves when None (a no-op without a survivor)."""
        if self.pipeline.survivor is None:
            return
        try:
            self.pipeline.survivor.command(move, face)
        except PlayerError as exc:
            raise SessionError(str(exc)) from None

    def strike(self) -> int:
        """The player strikes: the survivor swings its bat (its blow lands on the nearest zombie within
        reach when the swing does; returns -1), or, without one, the nearest living zombie within reach is
        hit at once (returns it, or -1)."""
        if self.pipeline.survivor is not None:
            self.pipeline.survivor.strike()
            return -1
        ai = self.pipeline.crowd_ai
        return ai.strike_nearest(ai.player, STRIKE_REACH)

    def hud(self) -> dict | None:
        """What the game's heads-up display shows of the survivor (None without one): health, kills, the
        living zombies within notice radius, the round and its time, the best time survived."""
        s = self.pipeline.survivor
        if s is None:
            return None
        ai = self.pipeline.ai
        r = ai.config.notice_radius
        if self.pipeline.gpu_crowd is not None:
            near = self.pipeline.gpu_crowd.near_player()
        else:
            near = int(np.count_nonzero(((ai.x - s.position[0]) ** 2 + (ai.z - s.position[1]) ** 2 < r * r) & ai.alive())) if ai.n else 0
        return {"health": s.health, "health_max": HEALTH, "kills": s.kills, "near": near, "round": s.rounds,
                "time_s": s.round_time, "best_s": max(s.best_time, s.round_time)}

    def markers(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The rings the window draws on the ground: the player (red) and the selected agent (yellow).
        Returns world points (M, 3) float64, radii (M,) and linear RGBA colours (M, 4)."""
        ai = self.pipeline.ai
        points = [(ai.player[0], 0.0, ai.player[1])]
        radii = [0.6 if self.pipeline.survivor is None else 0.75]  # (around the survivor's feet)
        colors = [(0.9, 0.15, 0.1, 1.0)]
        row = self._agent_row(self.selected) if 0 <= self.selected < ai.n else None
        if row is not None:
            points.append((row["x"], 0.0, row["z"]))
            radii.append(0.55 * row["scale"])
            colors.append((1.0, 0.85, 0.2, 1.0))
        return np.array(points), np.array(radii), np.array(colors)

    # -- what the panel shows

    def inspect(self, agent: int | None = None) -> dict | None:
        """State, layers, weights, phase and weapon of an agent (the selected one by default)."""
        a = self.selected if agent is None else int(agent)
        ai = self.pipeline.ai
        if not 0 <= a < ai.n:
            return None
        row = self._agent_row(a)
        if row is None:
            return None
        layers = self.pipeline.layer_row(a)
        character = self.character_of(a)
        names = self.clip_names(character)
        weapon = int(ai.weapon[a])
        weapons = cast_weapons([m.character for m in self.pipeline.cast])[1]
        return {
            "agent": a,
            "character": self.pipeline.cast[character].name,
            "state": STATE_NAMES[row["state"]],
            "position": (row["x"], row["z"]),
            "speed": float(math.hypot(row["vx"], row["vz"])),
            "health": row["health"],
            "phase": row["phase"],
            "layers": [{"clip": names[int(l[CLIP])], "phase": float(l[PHASE]), "weight": float(l[WEIGHT]), "mask": int(l[MASK])}
                       for l in layers],
            "weapon": weapons[weapon] if 0 <= weapon < len(weapons) else None,
        }

    def to_scene(self) -> Scene:
        """The scene as it stands now, with every tweak made in the panel."""
        p = self.pipeline
        cam = p.camera
        characters = []
        for entry, member in zip(self.scene.characters, p.cast):
            bake_loops = {c.name: c.loop for c in member.bake.clips}
            authored = {c.name: c.loop for c in member.character.clips if c.name in bake_loops}
            characters.append(dataclasses.replace(entry, clip_speed=dict(member.clip_speed),
                                                  clip_loop={k: v for k, v in bake_loops.items() if authored.get(k) != v}))
        return dataclasses.replace(
            self.scene, characters=tuple(characters), agents=p.agents, seed=p.config.seed, bake_fps=p.bake.fps, precision=p.bake.precision,
            compression_bound_mm=p.bake.bound_mm, interpolation=p.processor.interpolation, ai=p.ai.config,
            weapons=p.config.weapons, readback_latency=p.latency, shadows=p.renderer.shadows, culling=p.renderer.culling, occlusion=p.config.occlusion,
            lod_distances=tuple(p.renderer.lod_distances), processor=p.config.processor_path, ai_path=p.config.ai_path, cull=p.config.cull, gl=p.config.gl, foot_lock=p.config.foot_lock,
            survivor=p.survivor is not None, town=p.town is not None, morphs=p.config.morphs, impostors=p.config.impostors,
            impostor_distance=p.config.impostor_distance, lod_fade=p.config.lod_fade, lod_error_px=p.config.lod_error_px,
            camera=CameraSetting(tuple(float(v) for v in cam.eye), tuple(float(v) for v in cam.target), float(cam.fov_y)))

    def save(self, path) -> Path | None:
        """Write the current tweaks to a scene file (atomically, keeping the previous one as .bak)."""
        return save_scene(self.to_scene(), path)

    def release(self) -> None:
        if self._rebake is not None:  # its thread touches no GL; it is waited for so nothing outlives the session
            self._rebake["thread"].join()
            self._rebake = None
        if self.pipeline is not None and self._owns_pipeline:
            self.pipeline.release()
