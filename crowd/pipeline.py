"""One frame of the crowd, stage after stage: ai → read back → upload → process → gather → cull/LOD →
attach → shadow → draw → weapons → ground.

``CrowdPipeline`` owns one instance of each stage and nothing else; each stage owns its GL objects.
The headless smoke mode, the window (through crowd.session) and the benchmarks drive this same class.

Weapons (when the scene has armed agents): frame F gathers the sockets of its armed agents and the
CPU reads those of frame F - N (N = ``readback_latency``, 1 to 3). Each body is drawn with the palette
of frame F - N too (the processor keeps N + 1 palettes), so the weapon and the hand come from the same
matrix: the pose shown lags the simulation by N frames, and nothing else does (positions and headings
are this frame's). Agents that (re)spawned after frame F - N are drawn with this frame's palette and
without a weapon until their own history reaches back that far; the first N frames show no weapons.
Without armed agents there is no gather pass, no read-back buffer and a single palette.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import moderngl
import numpy as np

from .gltf import load_character
from .ai import LAYERS, AIConfig, CrowdAI, PlayerScript, motion_for, upper_body_mask
from .bake import DEFAULT_FPS
from .processor import DEFAULT_INTERPOLATION, AnimationProcessor, palette_joint_positions
from .readback import RING, SocketReadback
from .render import DEFAULT_LOD_DISTANCES, Camera, CrowdRenderer
from .roles import bake_roles, match_roles
from .timing import PassTimer
from .weapons import AgentFrames, WeaponRenderer

MAX_AGENTS = 1_000_000


class PipelineError(ValueError):
    """Bad pipeline configuration; the message is one line."""


@dataclass
class PipelineConfig:
    agents: int = 200
    seed: int = 1
    model: Path | None = None
    roles: dict = field(default_factory=dict)
    bake_fps: float | str = DEFAULT_FPS  # or "source": each clip at its own key rate
    precision: str = "f32"
    interpolation: str = DEFAULT_INTERPOLATION
    processor_path: str = "auto"
    shadows: bool = True
    culling: bool = True
    lod_distances: tuple = DEFAULT_LOD_DISTANCES
    ai: AIConfig = field(default_factory=AIConfig)
    origin: tuple = (0.0, 0.0)  # world centre (x, z) in metres; float64 all the way to the camera subtraction
    scripted_player: bool = True  # headless: the player walks a circle and strikes; the window moves it instead
    weapons: bool = True  # armed agents carry weapons (AIConfig.armed_share says how many)
    readback_latency: int = 2  # frames between gathering a socket and the CPU reading it (1 to 3)


class CrowdPipeline:
    def __init__(self, ctx: moderngl.Context, config: PipelineConfig):
        if not isinstance(config.agents, int) or not 0 <= config.agents <= MAX_AGENTS:
            raise PipelineError(f"agent count must be 0 to {MAX_AGENTS}, got {config.agents!r}")
        self.ctx = ctx
        self.config = config
        self.character = load_character(config.model)
        self.roles, self.role_notes = match_roles(self.character.clips, config.roles)
        # Leave out what the scene does not need: only the clips the roles play are baked.
        self.bake = bake_roles(self.character, self.roles, config.bake_fps, config.precision)
        masks = upper_body_mask(self.character.skeleton)
        self.latency = _check_latency(config.readback_latency)
        # Leave out what the scene does not need: no weapons, no socket, or nobody armed → no read-back
        # stage, no gather pass, no weapon meshes, and one palette instead of a ring.
        armed = self._armed(config)
        self._masks = masks
        self.clip_speed: dict[str, float] = {}  # clip name → playback speed (time scale), where not 1
        self.layer_override = None  # callable(layers) applied after the AI wrote them (the panel's force clip and weights)
        self.processor = AnimationProcessor(ctx, self.bake, LAYERS, masks=masks, path=config.processor_path,
                                            history=self.latency + 1 if armed else 1, interpolation=config.interpolation)
        self.renderer = self._make_renderer()
        self.motion = motion_for(self.character, self.bake, self.roles)
        self.ai = CrowdAI(config.agents, config.seed, self.motion, config.ai, config.origin)
        self.player_script = PlayerScript(self.ai.half_extent * 0.5) if config.scripted_player else None
        self._layers = np.empty((config.agents, LAYERS, 4), np.float32)
        self.processor.resize(config.agents)
        self.readback = SocketReadback(ctx, self.bake.joint_count, self.processor.agents_per_row) if armed else None
        self.weapons = WeaponRenderer(ctx, self.character, config.shadows) if armed else None
        self._palette_frames: deque = deque(maxlen=self.processor.history)  # the frame of each kept palette, oldest first
        self._born = np.zeros(config.agents, np.int64)  # frame in which each agent (re)spawned
        self._read = None  # this frame's read-back (frame F - N), or None
        self._row_offset = 0  # palette rows each agent was drawn from
        self.readback_waits: list[float] = []
        self.readback_stalls = 0
        self._pose_lag: deque = deque(maxlen=RING + 1)  # simulated seconds of the last frames
        self.timer = PassTimer(ctx)
        self.frames = 0
        self.passes_run: list[str] = []
        self.camera = self.default_camera(16 / 9)

    @property
    def agents(self) -> int:
        return self.ai.n

    def _armed(self, config: PipelineConfig) -> bool:
        return config.weapons and config.ai.armed_share > 0 and bool(self.character.props) and bool(self.character.sockets)

    # -- run-time settings: the panel and the command line both come through these

    def _make_renderer(self) -> CrowdRenderer:
        c = self.config
        return CrowdRenderer(self.ctx, self.character, self.bake.joint_count, self.processor.agents_per_row,
                             lod_distances=c.lod_distances, shadows=c.shadows, culling=c.culling)

    def _set_palette_history(self, history: int) -> None:
        """A new palette ring: the frames kept and the read-backs queued against the old one are gone."""
        self.processor.set_history(history)
        self._palette_frames = deque(maxlen=self.processor.history)
        if self.readback is not None:
            self.readback.reset()

    def set_shadows(self, on: bool) -> None:
        """Shadows decide the shaders and the shadow map, so switching them builds the renderer (and
        the weapons' programs) again; the old objects are released."""
        if bool(on) == self.renderer.shadows:
            return
        self.config = dataclasses.replace(self.config, shadows=bool(on))
        old, self.renderer = self.renderer, self._make_renderer()
        old.release()
        if self.weapons is not None:
            self.weapons.release()
            self.weapons = WeaponRenderer(self.ctx, self.character, self.config.shadows)

    def set_culling(self, on: bool) -> None:
        self.config = dataclasses.replace(self.config, culling=bool(on))
        self.renderer.culling = bool(on)

    def set_lod_distances(self, near: float, far: float) -> None:
        if not (np.isfinite(near) and np.isfinite(far) and 0 < near <= far):
            raise PipelineError(f"LOD distances must be two increasing positive numbers, got {near!r}, {far!r}")
        self.config = dataclasses.replace(self.config, lod_distances=(float(near), float(far)))
        self.renderer.lod_distances = (float(near), float(far))

    def set_weapons(self, on: bool) -> None:
        """Weapons on: the read-back stage, weapon meshes and a palette ring appear; off: all of them go."""
        self.config = dataclasses.replace(self.config, weapons=bool(on))
        armed = self._armed(self.config)
        if armed == (self.readback is not None):
            return
        if armed:
            self.readback = SocketReadback(self.ctx, self.bake.joint_count, self.processor.agents_per_row)
            self.weapons = WeaponRenderer(self.ctx, self.character, self.config.shadows)
        else:
            self.readback.release()
            self.weapons.release()
            self.readback = self.weapons = None
            self._read = None
        self._set_palette_history(self.latency + 1 if armed else 1)

    def set_ai_config(self, config: AIConfig) -> None:
        self.ai.set_config(config)
        self.config = dataclasses.replace(self.config, ai=self.ai.config)

    def rebake(self, fps: float | str, precision: str, interpolation: str | None = None) -> None:
        """Bake the scene's clips again at another rate or precision, or process them with another
        interpolation, live: a new bake and processor replace the old ones (released), and the crowd
        keeps its state."""
        interpolation = self.config.interpolation if interpolation is None else interpolation
        bake = bake_roles(self.character, self.roles, fps, precision)
        for i, clip in enumerate(bake.clips):  # loop settings made in the panel survive the re-bake
            old = next((c for c in self.bake.clips if c.name == clip.name), None)
            if old is not None:
                bake.clips[i] = dataclasses.replace(clip, loop=old.loop)
        processor = AnimationProcessor(self.ctx, bake, LAYERS, masks=self._masks, path=self.config.processor_path,
                                       history=self.processor.history, interpolation=interpolation)
        processor.resize(self.agents)
        self.processor.release()
        self.processor, self.bake = processor, bake
        self.config = dataclasses.replace(self.config, bake_fps=bake.fps, precision=precision, interpolation=interpolation)
        self._palette_frames.clear()
        if self.readback is not None:
            self.readback.reset()
        self.ai.set_motion(motion_for(self.character, self.bake, self.roles, self.clip_speed))
        self.motion = self.ai.motion

    def set_clip_speed(self, name: str, speed: float) -> None:
        """A clip's playback speed (three.js's timeScale). Locomotion clips move the zombie faster too, so
        their feet stay planted; actions end sooner."""
        self.bake.clip_index(name)
        speeds = {**self.clip_speed, name: float(speed)}
        motion = motion_for(self.character, self.bake, self.roles, speeds)  # checks the range
        self.clip_speed = {k: v for k, v in speeds.items() if v != 1.0}
        self.ai.set_motion(motion)
        self.motion = motion

    def set_clip_loop(self, name: str, loop: bool) -> None:
        self.processor.set_clip_loop(self.bake.clip_index(name), loop)

    def set_agent_count(self, agents: int) -> None:
        if not isinstance(agents, (int, np.integer)) or not 0 <= agents <= MAX_AGENTS:
            raise PipelineError(f"agent count must be 0 to {MAX_AGENTS}, got {agents!r}")
        old = self.ai.n
        self.ai.resize(int(agents))
        self.processor.resize(int(agents))
        self._layers = np.empty((int(agents), LAYERS, 4), np.float32)
        born = np.full(int(agents), self.frames, np.int64)
        born[: min(old, int(agents))] = self._born[: min(old, int(agents))]
        self._born = born
        self.config = dataclasses.replace(self.config, agents=int(agents))

    def set_seed(self, seed: int) -> None:
        """A new crowd from another seed (same count, settings and clips); every agent starts anew."""
        self.config = dataclasses.replace(self.config, seed=int(seed))
        self.ai = CrowdAI(self.agents, int(seed), self.motion, self.ai.config, self.config.origin)
        self._born[:] = self.frames

    def set_readback_latency(self, latency: int) -> None:
        """1 to 3 frames. The palette ring is reallocated, so weapons are hidden for `latency` frames."""
        self.latency = _check_latency(latency)
        if self.readback is not None:
            self._set_palette_history(self.latency + 1)

    def default_camera(self, aspect: float) -> Camera:
        """A three-quarter view that frames the whole crowd (or one agent up close)."""
        extent = max(self.ai.half_extent, 1.2)
        dist = extent * 1.5 + 2.5
        centre = np.array([self.ai.origin[0], 0.0, self.ai.origin[1]])
        eye = centre + np.array([dist * 0.45, dist * 0.5, dist * 0.85])
        return Camera(eye=eye, target=centre + np.array([0.0, 0.8, 0.0]), aspect=aspect, far=max(200.0, dist * 4))

    def _run(self, name: str) -> None:
        if name not in self.passes_run:
            self.passes_run.append(name)

    def frame(self, framebuffer: moderngl.Framebuffer, dt: float) -> None:
        t = self.timer
        f = self.frames
        with t.cpu("ai"):
            if self.player_script is not None:
                self.player_script.update(self.ai)
            steps_before = self.ai.steps
            self.ai.step(dt)
            instances = self.ai.instances()
            layers = self.ai.write_layers(self._layers)
            if self.layer_override is not None:
                self.layer_override(layers)
        self._run("ai")
        self._born[self.ai.spawned_step >= steps_before] = f  # respawned (or added) in this frame's step
        self._pose_lag.append(float(min(dt, self.ai.config.max_dt)))
        if self.readback is not None:
            # Before this frame's gather: with N = 3 the slot read now is the one written next.
            with t.cpu("readback"):
                self._read = self.readback.fetch(f - self.latency)
            self._run("readback")
            if self._read is not None:
                self.readback_waits.append(self._read.wait_ms)
                self.readback_stalls += int(self._read.stalled)
        with t.cpu("upload"):
            self.processor.upload(layers)
        if self.agents:
            with t.gpu("process"):
                self.processor.run()
            self._run("process")
            if self.processor.runs == 1:  # a new palette: the frames kept before it are gone
                self._palette_frames.clear()
            self._palette_frames.append(f)
        if self.readback is not None and self.agents:
            armed = np.flatnonzero(self.ai.armed())
            if self.readback.gather(f, self.processor, armed, np.full(armed.size, self.weapons.socket_joint), t):
                self._run("gather")
                self._run("transfer")
        # Each body's palette: frame F - N where the weapon read-back is from that frame, else this one.
        self._row_offset = 0
        if self.agents:
            self._row_offset = self.processor.row_offset(0)
            if self._read is not None and self._read.frame in self._palette_frames:
                age = len(self._palette_frames) - 1 - list(self._palette_frames).index(self._read.frame)
                old = self.processor.row_offset(age)
                self._row_offset = np.where(self._born <= self._read.frame, old, self._row_offset).astype(np.uint32)
        with t.cpu("cull_lod"):
            view_proj = self.renderer.prepare(self.camera, instances, self._row_offset)
        self._run("cull_lod")
        if self.weapons is not None:
            with t.cpu("attach"):
                read = self._synced_read()
                self._frames = AgentFrames(instances.position, instances.yaw, instances.scale, self.camera.eye)
                self.weapons.attach(read, self._frames, self.ai.weapon, self.renderer.visible)
            self._run("attach")
        framebuffer.use()
        framebuffer.clear(*self.renderer.clear_color(), 1.0, depth=1.0)
        if self.renderer.shadows:
            with t.gpu("shadow"):
                self.renderer.shadow_pass(self.camera, self.processor)
                if self.weapons is not None and self.weapons.last["weapons"]:
                    self.weapons.depth_pass(self.renderer.light)
            self._run("shadow")
        if self.renderer.last["instances"]:
            with t.gpu("draw"):
                self.renderer.color_pass(framebuffer, view_proj, self.processor)
            self._run("draw")
        if self.weapons is not None and self.weapons.last["weapons"]:
            with t.gpu("weapons"):
                self.weapons.color_pass(framebuffer, view_proj, self.renderer)
            self._run("weapons")
        with t.gpu("ground"):
            self.renderer.ground_pass(framebuffer, self.camera, view_proj)
        self._run("ground")
        t.end_frame()
        self.frames += 1

    def _synced_read(self):
        """This frame's read-back, limited to agents whose body is drawn with the palette of its frame
        (those that existed then); None when that palette is gone."""
        read = self._read
        if read is None or read.frame not in self._palette_frames:
            return None
        keep = read.agents < self.agents
        keep[keep] = self._born[read.agents[keep]] <= read.frame
        return dataclasses.replace(read, agents=read.agents[keep], joints=read.joints[keep], rows=read.rows[keep])

    def weapon_error_mm(self, body: str = "drawn") -> float | None:
        """Largest distance (mm) between a drawn weapon's grip point and its agent's socket point on the
        body, both as the GPU got them (synchronous palette read: tests, stats and benchmarks only).
        body="latest" measures against the newest palette instead: the error of drawing the body
        unsynchronised with the read-back. None when no weapon was drawn."""
        if self.weapons is None or not self.weapons.last["weapons"]:
            return None
        agents, weapon, _ = self.weapons.drawn
        if body == "drawn":
            offsets = np.broadcast_to(np.asarray(self._row_offset, np.int64), (self.agents,))[agents]
        else:
            offsets = np.full(len(agents), self.processor.row_offset(0), np.int64)
        rows = self.processor.read_rows(agents, self.weapons.socket_joint, offsets).astype(np.float64)
        socket_model = np.einsum("kij,j->ki", rows, self.weapons.socket_bind[:, 3])
        hand = self._frames.points(agents, socket_model)
        return float(np.max(np.linalg.norm(hand - self.weapons.grip_points(), axis=1)) * 1e3)

    def project(self, world: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """Pixel (x, y from the top-left) of world points (P, 3) in this frame's camera."""
        rel = np.asarray(world, np.float64) - np.asarray(self.camera.eye, np.float64)
        clip = np.c_[rel, np.ones(len(rel))] @ self.camera.view_proj().astype(np.float64).T
        ndc = clip[:, :3] / clip[:, 3:4]
        return np.stack([(ndc[:, 0] * 0.5 + 0.5) * size[0], (0.5 - ndc[:, 1] * 0.5) * size[1]], axis=1)

    def joint_world_positions(self, joint: int) -> np.ndarray:
        """World position of one joint of every agent, from the GPU palette (synchronous; tests, stats)."""
        pal = self.processor.read_palette()
        model = palette_joint_positions(pal[:, joint : joint + 1], self.character.skeleton.inverse_bind[joint : joint + 1])[:, 0]
        yaw = self.ai.yaw
        c, s = np.cos(yaw), np.sin(yaw)
        rotated = np.stack([c * model[:, 0] + s * model[:, 2], model[:, 1], -s * model[:, 0] + c * model[:, 2]], axis=1)
        ground = np.stack([self.ai.x, np.zeros(self.ai.n), self.ai.z], axis=1)
        return ground + self.ai.scale[:, None].astype(np.float64) * rotated

    def gpu_bytes(self) -> dict[str, int]:
        out = dict(self.processor.gpu_bytes())
        out.update(self.renderer.gpu_bytes())
        if self.readback is not None:
            out["readback"] = self.readback.gpu_bytes()
        if self.weapons is not None:
            out["weapons"] = self.weapons.gpu_bytes()
        return out

    def stats(self) -> dict:
        return {
            "agents": self.agents,
            "processor_path": self.processor.path,
            "layers": self.processor.layer_count,
            "bake": {"fps": self.bake.fps, "precision": self.bake.precision, "interpolation": self.processor.interpolation,
                     "clips": [c.name for c in self.bake.clips],
                     "rows": self.bake.rows, "bytes": self.bake.nbytes},
            "roles": self.roles,
            "ai": {"states": self.ai.counts(), "player_hits_taken": self.ai.player_hits_taken, "faults": self.ai.check(),
                   "notes": list(self.motion.notes)},
            "passes_ms": self.timer.medians(),
            "passes_clock": {k: self.timer.clock[k] for k in self.timer.order},
            "passes_run": list(self.passes_run),
            "gpu_bytes": self.gpu_bytes(),
            "last_frame": dict(self.renderer.last),
            "weapons": self.weapon_stats(),
            "weapon_error_mm": None if self.weapons is None else _round(self.weapon_error_mm()),
            "readback_wait_ms": self.readback_wait(),
        }

    def readback_wait(self) -> dict | None:
        if self.readback is None:
            return None
        waits = np.asarray(self.readback_waits or [0.0])
        return {"max": round(float(waits.max()), 4), "median": round(float(np.median(waits)), 4)}

    def weapon_stats(self) -> dict:
        if self.weapons is None:
            return {"enabled": False}
        return {"enabled": True, "latency_frames": self.latency,
                "pose_lag_ms": round(sum(list(self._pose_lag)[-self.latency:]) * 1e3, 3),  # simulated time the pose trails by
                "armed": int(np.count_nonzero(self.ai.armed())), "drawn": self.weapons.last["weapons"],
                "triangles": self.weapons.last["triangles"],
                "gathered": self.readback.last_count, "stalls": self.readback_stalls, "reads": len(self.readback_waits)}

    def release(self) -> None:
        self.timer.release()
        if self.weapons is not None:
            self.weapons.release()
        if self.readback is not None:
            self.readback.release()
        self.renderer.release()
        self.processor.release()


def smoke_size(text: str) -> tuple[int, int]:
    w, sep, h = text.lower().partition("x")
    try:
        size = (int(w), int(h))
    except ValueError:
        raise PipelineError(f"size must look like 1280x720, got {text!r}") from None
    if not sep or not (16 <= size[0] <= 8192 and 16 <= size[1] <= 8192):
        raise PipelineError(f"size must be WxH with each side 16 to 8192, got {text!r}")
    return size


def _check_latency(latency) -> int:
    if isinstance(latency, bool) or latency not in range(1, RING + 1):
        raise PipelineError(f"readback latency must be 1 to {RING} frames, got {latency!r}")
    return int(latency)


def _round(value, digits: int = 5):
    return None if value is None else round(float(value), digits)


def percentiles(values) -> dict:
    a = np.asarray(values, np.float64)
    if a.size == 0:
        return {"p50": None, "p95": None, "max": None}
    return {"p50": round(float(np.percentile(a, 50)), 4), "p95": round(float(np.percentile(a, 95)), 4), "max": round(float(a.max()), 4)}

