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
from pathlib import Path

import moderngl
import numpy as np

from .ai import STATE_NAMES, AIError
from .bake import SOURCE_RATE, BakeError
from .pipeline import CrowdPipeline, PipelineError
from .processor import CLIP, INTERPOLATIONS, MASK, PHASE, WEIGHT
from .render import Camera
from .scene import CameraSetting, Scene, SceneError, save_scene

MAX_TIME_SCALE = 10.0
STRIKE_REACH = 2.0  # metres from the player
PICK_RADIUS = 0.4  # metres: an agent is a vertical cylinder this wide and 1.9 m tall (times its scale)
PICK_HEIGHT = 1.9


class SessionError(ValueError):
    """A control given a value it cannot take; the message is one line."""


class OrbitControl:
    """Orbit, pan and zoom around a target point, the way editors do: drag to orbit, drag with the
    middle button (or shift) to pan along the ground, scroll to zoom. Writes a render Camera."""

    def __init__(self, camera: Camera):
        eye, target = np.asarray(camera.eye, np.float64), np.asarray(camera.target, np.float64)
        offset = eye - target
        self.target = target.copy()
        self.distance = float(np.linalg.norm(offset))
        self.yaw = math.atan2(offset[0], offset[2])
        self.pitch = math.asin(max(-1.0, min(1.0, offset[1] / max(self.distance, 1e-9))))

    def orbit(self, dx: float, dy: float) -> None:
        """Pixels dragged: 0.3 degrees per pixel; the pitch stays between 3 and 89 degrees."""
        self.yaw -= math.radians(0.3 * dx)
        self.pitch = min(math.radians(89.0), max(math.radians(3.0), self.pitch + math.radians(0.3 * dy)))

    def pan(self, dx: float, dy: float) -> None:
        """Move the target along the ground, a distance proportional to how far the camera is."""
        k = 0.0015 * self.distance
        right = np.array([math.cos(self.yaw), 0.0, -math.sin(self.yaw)])
        forward = np.array([-math.sin(self.yaw), 0.0, -math.cos(self.yaw)])
        self.target += (-dx * right + dy * forward) * k

    def zoom(self, steps: float) -> None:
        self.distance = min(5000.0, max(1.5, self.distance * (0.88 ** steps)))

    def apply(self, camera: Camera) -> None:
        cp = math.cos(self.pitch)
        offset = self.distance * np.array([cp * math.sin(self.yaw), math.sin(self.pitch), cp * math.cos(self.yaw)])
        camera.target = self.target.copy()
        camera.eye = self.target + offset
        camera.far = max(400.0, self.distance * 4.0)


class CrowdSession:
    def __init__(self, ctx: moderngl.Context, scene: Scene, aspect: float = 16 / 9, scripted_player: bool = False):
        self.ctx = ctx
        self.scene = scene
        config = dataclasses.replace(scene.pipeline_config(), scripted_player=scripted_player)
        self.pipeline = CrowdPipeline(ctx, config)
        try:
            for name, speed in scene.clip_speed.items():
                self.pipeline.set_clip_speed(name, speed)
            for name, loop in scene.clip_loop.items():
                self.pipeline.set_clip_loop(name, loop)
        except (BakeError, AIError) as exc:
            self.pipeline.release()
            raise SceneError(f"scene {scene.name!r}: {exc}") from None
        self.pipeline.camera = scene.camera_for(aspect) or self.pipeline.default_camera(aspect)
        self.paused = False
        self.time_scale = 1.0
        self.selected = -1
        self.forced: dict | None = None  # {"clip": index, "agents": None (all) or array, "start": time}
        self.held_weights: dict = {}  # layer → (weight, agents or None)
        self.bake_error: dict | None = None  # the last measure_error(), until the next re-bake
        self._pending_steps = 0
        self.pipeline.layer_override = self._override_layers

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
        self.pipeline.frame(framebuffer, sim)
        return sim

    def set_paused(self, paused: bool) -> None:
        self.paused = bool(paused)

    def step_once(self) -> None:
        """While paused: the next frame advances one 1/60 s step."""
        self.paused = True
        self._pending_steps += 1

    def set_time_scale(self, scale: float) -> None:
        if not math.isfinite(scale) or not 0.0 <= scale <= MAX_TIME_SCALE:
            raise SessionError(f"time scale must be 0 to {MAX_TIME_SCALE:g}, got {scale!r}")
        self.time_scale = float(scale)

    # -- crowd

    def set_agent_count(self, agents: int) -> None:
        try:
            self.pipeline.set_agent_count(int(agents))
        except (PipelineError, ValueError) as exc:
            raise SessionError(str(exc)) from None
        if self.selected >= self.pipeline.agents:
            self.selected = -1

    def set_seed(self, seed: int) -> None:
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
            raise SessionError(f"seed must be a whole number, got {seed!r}")
        self.pipeline.set_seed(int(seed))

    def set_ai(self, **settings) -> None:
        """AI settings by name (cross-fade length: crossfade=0.4)."""
        try:
            self.pipeline.set_ai_config(dataclasses.replace(self.pipeline.ai.config, **settings))
        except (AIError, TypeError) as exc:
            raise SessionError(str(exc).splitlines()[0]) from None

    def set_crossfade(self, seconds: float) -> None:
        self.set_ai(crossfade=float(seconds))

    # -- clips

    def clip_names(self) -> list[str]:
        return [c.name for c in self.pipeline.bake.clips]

    def _clip(self, name: str) -> int:
        try:
            return self.pipeline.bake.clip_index(name)
        except BakeError as exc:
            raise SessionError(str(exc)) from None

    def set_clip_speed(self, name: str, speed: float) -> None:
        try:
            self.pipeline.set_clip_speed(name, speed)
        except (AIError, BakeError) as exc:
            raise SessionError(str(exc)) from None

    def set_clip_loop(self, name: str, loop: bool) -> None:
        try:
            self.pipeline.set_clip_loop(name, loop)
        except BakeError as exc:
            raise SessionError(str(exc)) from None

    def play(self, name: str | None, selected_only: bool = True) -> None:
        """Force a clip, from its start, on the selected agent (or on every agent); None gives control
        back to the AI."""
        if name is None:
            self.forced = None
            return
        if selected_only and self.selected < 0:
            raise SessionError("no agent selected: click one, or play the clip on all agents")
        self.forced = {"clip": self._clip(name), "agents": np.array([self.selected]) if selected_only else None,
                       "start": self.pipeline.ai.time}

    def set_weight(self, layer: int, weight: float | None, selected_only: bool = False) -> None:
        """Hold a layer's weight at a value (None: the AI decides again). Layers: 0 idle, 1 walk, 2 run, 3 action."""
        if not 0 <= layer < 4:
            raise SessionError(f"layer must be 0 to 3, got {layer!r}")
        if weight is None:
            self.held_weights.pop(layer, None)
            return
        if not math.isfinite(weight) or not 0.0 <= weight <= 1000.0:
            raise SessionError(f"weight must be 0 to 1000, got {weight!r}")
        if selected_only and self.selected < 0:
            raise SessionError("no agent selected")
        self.held_weights[layer] = (float(weight), np.array([self.selected]) if selected_only else None)

    def _override_layers(self, layers: np.ndarray) -> None:
        n = len(layers)
        if self.forced is not None:
            agents = self.forced["agents"]
            agents = slice(None) if agents is None else agents[agents < n]
            clip = self.forced["clip"]
            info = self.pipeline.bake.clips[clip]
            speed = self.pipeline.clip_speed.get(info.name, 1.0)
            phase = (self.pipeline.ai.time - self.forced["start"]) * speed / max(info.duration, 1e-6)
            layers[agents] = (0.0, 0.0, 0.0, -1.0)
            layers[agents, 0, CLIP] = clip
            layers[agents, 0, PHASE] = phase if info.loop else min(phase, 1.0)
            layers[agents, 0, WEIGHT] = 1.0
        for layer, (weight, agents) in self.held_weights.items():
            agents = slice(None) if agents is None else agents[agents < n]
            layers[agents, layer, WEIGHT] = weight

    # -- rendering features

    def rebake(self, fps: float | str, precision: str, interpolation: str | None = None) -> None:
        """Bake again at another rate ("source": each clip at its own key rate) or precision, or process
        with another interpolation."""
        rate_ok = fps == SOURCE_RATE or (isinstance(fps, (int, float)) and math.isfinite(fps) and 1.0 <= fps <= 240.0)
        if not rate_ok or precision not in ("f32", "f16") or interpolation not in (None, *INTERPOLATIONS):
            raise SessionError(f"bake rate must be 1 to 240 fps or {SOURCE_RATE!r}, precision f32 or f16 and interpolation one of "
                               f"{', '.join(INTERPOLATIONS)}; got {fps!r}, {precision!r}, {interpolation!r}")
        try:
            self.pipeline.rebake(fps if fps == SOURCE_RATE else float(fps), precision, interpolation)
        except BakeError as exc:
            raise SessionError(str(exc)) from None
        self.bake_error = None

    def measure_error(self, per_clip: int = 24, blends: int = 240) -> dict:
        """The shell error of the current bake and interpolation on this GPU against the float64
        reference (crowd.accuracy), over the scene's clips alone and in random blends: what the panel
        shows next to the bake settings. A few hundred poses: tens of milliseconds on llvmpipe."""
        from . import accuracy

        p = self.pipeline
        # The reference plays each clip as the bake does (loop settings changed in the panel included).
        clips = [dataclasses.replace(p.character.clip(c.name), loop=c.loop) for c in p.bake.clips]
        samples = accuracy.draw_samples(clips, np.random.default_rng(0), per_clip, blends)
        truth = accuracy.truth(p.character.skeleton, clips, samples.layers)
        errors = accuracy.measure_gpu(self.ctx, p.character.skeleton, p.bake, samples.layers, truth, p.processor.interpolation)
        self.bake_error = {**accuracy.summarise(errors), "poses": int(len(samples.layers))}
        return self.bake_error

    def set_lod_distances(self, near: float, far: float) -> None:
        try:
            self.pipeline.set_lod_distances(near, far)
        except PipelineError as exc:
            raise SessionError(str(exc)) from None

    def set_culling(self, on: bool) -> None:
        self.pipeline.set_culling(on)

    def set_shadows(self, on: bool) -> None:
        self.pipeline.set_shadows(on)

    def set_weapons(self, on: bool) -> None:
        self.pipeline.set_weapons(on)

    def set_readback_latency(self, frames: int) -> None:
        try:
            self.pipeline.set_readback_latency(int(frames))
        except PipelineError as exc:
            raise SessionError(str(exc)) from None

    # -- the player and picking

    def ray(self, x: float, y: float, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """(origin, unit direction) in world space (float64) through pixel (x, y) from the top-left."""
        camera = self.pipeline.camera
        inv = np.linalg.inv(camera.view_proj().astype(np.float64))
        ndc = np.array([2.0 * x / size[0] - 1.0, 1.0 - 2.0 * y / size[1]])
        near = inv @ np.array([ndc[0], ndc[1], -1.0, 1.0])
        far = inv @ np.array([ndc[0], ndc[1], 1.0, 1.0])
        near, far = near[:3] / near[3], far[:3] / far[3]
        direction = far - near
        return np.asarray(camera.eye, np.float64) + near, direction / np.linalg.norm(direction)

    def pick(self, x: float, y: float, size: tuple[int, int]) -> int:
        """Select the agent under pixel (x, y): the nearest whose upright cylinder the ray enters. -1 and
        no selection when the ray misses every agent."""
        ai = self.pipeline.ai
        self.selected = -1
        if not ai.n:
            return -1
        origin, d = self.ray(x, y, size)
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

    def move_player(self, point) -> None:
        """Put the player at a ground point (x, z), kept inside the world."""
        p = np.asarray(point, np.float64).reshape(-1)
        if p.shape != (2,) or not np.all(np.isfinite(p)):
            raise SessionError("the player needs a finite ground point (x, z)")
        ai = self.pipeline.ai
        ai.player = np.clip(p, ai.origin - ai.half_extent, ai.origin + ai.half_extent)

    def strike(self) -> int:
        """The player strikes the nearest living zombie within reach; returns it, or -1."""
        ai = self.pipeline.ai
        target = ai.nearest_alive(ai.player, STRIKE_REACH)
        if target >= 0:
            ai.hit([target])
        return target

    def draw_markers(self, framebuffer) -> None:
        """The player (red ring) and the selected agent (yellow ring) on the ground."""
        p = self.pipeline
        ai = p.ai
        points = [(ai.player[0], 0.0, ai.player[1])]
        radii = [0.6]
        colors = [(0.9, 0.15, 0.1, 1.0)]
        if 0 <= self.selected < ai.n:
            points.append((ai.x[self.selected], 0.0, ai.z[self.selected]))
            radii.append(0.55 * float(ai.scale[self.selected]))
            colors.append((1.0, 0.85, 0.2, 1.0))
        p.renderer.marker_pass(framebuffer, p.camera, p.camera.view_proj(), np.array(points), np.array(radii), np.array(colors))

    # -- what the panel shows

    def inspect(self, agent: int | None = None) -> dict | None:
        """State, layers, weights, phase and weapon of an agent (the selected one by default)."""
        a = self.selected if agent is None else int(agent)
        ai = self.pipeline.ai
        if not 0 <= a < ai.n:
            return None
        layers = self.pipeline._layers[a]
        names = self.clip_names()
        weapon = int(ai.weapon[a])
        return {
            "agent": a,
            "state": STATE_NAMES[int(ai.state[a])],
            "position": (float(ai.x[a]), float(ai.z[a])),
            "speed": float(math.hypot(ai.vx[a], ai.vz[a])),
            "health": int(ai.health[a]),
            "phase": float(ai.phase[a]),
            "layers": [{"clip": names[int(l[CLIP])], "phase": float(l[PHASE]), "weight": float(l[WEIGHT]), "mask": int(l[MASK])}
                       for l in layers],
            "weapon": list(self.pipeline.character.props)[weapon] if weapon >= 0 else None,
        }

    def to_scene(self) -> Scene:
        """The scene as it stands now, with every tweak made in the panel."""
        p = self.pipeline
        cam = p.camera
        bake_loops = {c.name: c.loop for c in p.bake.clips}
        authored = {c.name: c.loop for c in p.character.clips if c.name in bake_loops}
        return dataclasses.replace(
            self.scene, agents=p.agents, seed=p.config.seed, bake_fps=p.bake.fps, precision=p.bake.precision,
            interpolation=p.processor.interpolation,
            roles=dict(p.config.roles), clip_speed=dict(p.clip_speed),
            clip_loop={k: v for k, v in bake_loops.items() if authored.get(k) != v}, ai=p.ai.config,
            weapons=p.config.weapons, readback_latency=p.latency, shadows=p.renderer.shadows, culling=p.renderer.culling,
            lod_distances=tuple(p.renderer.lod_distances), processor=p.config.processor_path,
            camera=CameraSetting(tuple(float(v) for v in cam.eye), tuple(float(v) for v in cam.target), float(cam.fov_y)))

    def save(self, path) -> Path | None:
        """Write the current tweaks to a scene file (atomically, keeping the previous one as .bak)."""
        return save_scene(self.to_scene(), path)

    def release(self) -> None:
        self.pipeline.release()
