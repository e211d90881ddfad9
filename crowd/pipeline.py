"""One frame of the crowd, stage after stage: ai → upload → process → cull/LOD → shadow → draw → ground.

``CrowdPipeline`` owns one instance of each stage and nothing else; each stage owns its GL objects.
The headless smoke mode, the window (issue 6) and the benchmarks drive this same class.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import moderngl
import numpy as np

from .gltf import load_character
from .ai import LAYERS, AIConfig, CrowdAI, PlayerScript, motion_for, upper_body_mask
from .processor import AnimationProcessor, palette_joint_positions
from .render import DEFAULT_LOD_DISTANCES, Camera, CrowdRenderer
from .roles import bake_roles, match_roles
from .timing import PassTimer

MAX_AGENTS = 1_000_000


class PipelineError(ValueError):
    """Bad pipeline configuration; the message is one line."""


@dataclass
class PipelineConfig:
    agents: int = 200
    seed: int = 1
    model: Path | None = None
    roles: dict = field(default_factory=dict)
    bake_fps: float = 15.0
    precision: str = "f32"
    processor_path: str = "auto"
    shadows: bool = True
    culling: bool = True
    lod_distances: tuple = DEFAULT_LOD_DISTANCES
    ai: AIConfig = field(default_factory=AIConfig)
    origin: tuple = (0.0, 0.0)  # world centre (x, z) in metres; float64 all the way to the camera subtraction
    scripted_player: bool = True  # headless: the player walks a circle and strikes; the window moves it instead


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
        self.processor = AnimationProcessor(ctx, self.bake, LAYERS, masks=masks, path=config.processor_path)
        self.renderer = CrowdRenderer(ctx, self.character, self.bake.joint_count, self.processor.agents_per_row,
                                      lod_distances=config.lod_distances, shadows=config.shadows, culling=config.culling)
        self.motion = motion_for(self.character, self.bake, self.roles)
        self.ai = CrowdAI(config.agents, config.seed, self.motion, config.ai, config.origin)
        self.player_script = PlayerScript(self.ai.half_extent * 0.5) if config.scripted_player else None
        self._layers = np.empty((config.agents, LAYERS, 4), np.float32)
        self.processor.resize(config.agents)
        self.timer = PassTimer(ctx)
        self.frames = 0
        self.passes_run: list[str] = []
        self.camera = self.default_camera(16 / 9)

    @property
    def agents(self) -> int:
        return self.ai.n

    def set_agent_count(self, agents: int) -> None:
        if not isinstance(agents, (int, np.integer)) or not 0 <= agents <= MAX_AGENTS:
            raise PipelineError(f"agent count must be 0 to {MAX_AGENTS}, got {agents!r}")
        self.ai.resize(int(agents))
        self.processor.resize(int(agents))
        self._layers = np.empty((int(agents), LAYERS, 4), np.float32)

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
        with t.cpu("ai"):
            if self.player_script is not None:
                self.player_script.update(self.ai)
            self.ai.step(dt)
            instances = self.ai.instances()
            layers = self.ai.write_layers(self._layers)
        self._run("ai")
        with t.cpu("upload"):
            self.processor.upload(layers)
        if self.agents:
            with t.gpu("process"):
                self.processor.run()
            self._run("process")
        with t.cpu("cull_lod"):
            view_proj = self.renderer.prepare(self.camera, instances)
        self._run("cull_lod")
        framebuffer.use()
        framebuffer.clear(*self.renderer.clear_color(), 1.0, depth=1.0)
        if self.renderer.shadows:
            with t.gpu("shadow"):
                self.renderer.shadow_pass(self.camera, self.processor)
            self._run("shadow")
        if self.renderer.last["instances"]:
            with t.gpu("draw"):
                self.renderer.color_pass(framebuffer, view_proj, self.processor)
            self._run("draw")
        with t.gpu("ground"):
            self.renderer.ground_pass(framebuffer, self.camera, view_proj)
        self._run("ground")
        t.end_frame()
        self.frames += 1

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
        return out

    def stats(self) -> dict:
        return {
            "agents": self.agents,
            "processor_path": self.processor.path,
            "layers": self.processor.layer_count,
            "bake": {"fps": self.bake.fps, "precision": self.bake.precision, "clips": [c.name for c in self.bake.clips],
                     "rows": self.bake.rows, "bytes": self.bake.nbytes},
            "roles": self.roles,
            "ai": {"states": self.ai.counts(), "player_hits_taken": self.ai.player_hits_taken, "faults": self.ai.check(),
                   "notes": list(self.motion.notes)},
            "passes_ms": self.timer.medians(),
            "passes_clock": {k: self.timer.clock[k] for k in self.timer.order},
            "passes_run": list(self.passes_run),
            "gpu_bytes": self.gpu_bytes(),
            "last_frame": dict(self.renderer.last),
        }

    def release(self) -> None:
        self.timer.release()
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


def percentiles(values) -> dict:
    a = np.asarray(values, np.float64)
    if a.size == 0:
        return {"p50": None, "p95": None, "max": None}
    return {"p50": round(float(np.percentile(a, 50)), 4), "p95": round(float(np.percentile(a, 95)), 4), "max": round(float(a.max()), 4)}

