"""What a crowd pipeline is built from: ``PipelineConfig`` (the scene's settings, as the pipeline takes
them), ``CharacterSpec`` (one character of the cast, as a scene names it) and ``PipelineError`` (a bad
configuration, in one line). Plain values: a scene file is read into them without building anything."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from .errors import CrowdError
from .settings import DEFAULTS
from .sim.config import AIConfig


class PipelineError(CrowdError, ValueError):
    """Bad pipeline configuration; the message is one line."""


@dataclass(frozen=True)
class CharacterSpec:
    """One character of a crowd as a scene names it: the model (None: the built-in zombie; a built-in's
    name, crowd.asset.gltf.BUILT_IN; or a glTF file), its share of the crowd (shares are relative), the
    roles its clips play (those its names do not match) and its size factor."""

    model: Path | str | None = None
    share: float = 1.0
    roles: dict = field(default_factory=dict)
    model_scale: float | str = DEFAULTS["model_scale"]
    morph: dict = field(default_factory=dict)  # morph target name → (lo, hi): each agent's offset (crowd.anim.morph)
    clips: tuple = ()  # glTF files whose clips join the model's, matched to its joints by name (crowd.asset.gltf.library)


@dataclass
class PipelineConfig:
    agents: int = DEFAULTS["agents"]
    seed: int = DEFAULTS["seed"]
    model: Path | None = None
    model_scale: float | str = DEFAULTS["model_scale"]  # a size factor, or "auto" (a person's height where the file is far off)
    roles: dict = field(default_factory=dict)
    bake_fps: float | str = DEFAULTS["bake_fps"]  # or "source": each clip at its own key rate
    precision: str = DEFAULTS["precision"]
    compression_bound_mm: float = DEFAULTS["compression_bound_mm"]  # the compressed bake's error bound (precision "compressed")
    interpolation: str = DEFAULTS["interpolation"]
    processor_path: str = DEFAULTS["processor"]
    ai_path: str = DEFAULTS["ai_path"]  # "auto", "gpu" or "cpu": where the crowd AI runs (crowd.sim.gpu, or the numpy AI)
    shadows: bool = DEFAULTS["shadows"]
    culling: bool = DEFAULTS["culling"]
    occlusion: bool = DEFAULTS["occlusion"]  # against the previous frame's depth pyramid (the gpu cull path)
    lod_distances: tuple = DEFAULTS["lod_distances"]
    ai: AIConfig = field(default_factory=AIConfig)
    origin: tuple = (0.0, 0.0)  # world centre (x, z) in metres; float64 all the way to the camera subtraction
    scripted_player: bool = True  # headless: the player walks a circle and strikes; the window moves it instead
    weapons: bool = DEFAULTS["weapons"]  # armed agents carry weapons (AIConfig.armed_share says how many)
    readback_latency: int = DEFAULTS["readback_latency"]  # frames between gathering a socket and the CPU reading it
    cull: str = DEFAULTS["cull"]  # "auto", "gpu" or "cpu": where culling, LOD and the instance lists are made
    gl: str = DEFAULTS["gl"]  # "auto" or "4.1": the GL features the stages may use (crowd.gl.feature_level)
    foot_lock: bool = DEFAULTS["foot_lock"]  # planted feet held by the processor (the compute path; crowd.anim.foot_lock)
    morphs: bool = DEFAULTS["morphs"]  # morph targets drawn where the scene moves them (crowd.anim.morph, crowd.draw.morph)
    impostors: str = DEFAULTS["impostors"]  # "auto", "on" or "off": far agents drawn as impostors (crowd.draw.impostors)
    impostor_distance: float = DEFAULTS["impostor_distance"]  # metres from the camera
    lod_fade: float = DEFAULTS["lod_fade"]  # metres past each LOD switch over which the two LODs cross-fade
    lod_error_px: float = DEFAULTS["lod_error_px"]  # pixels of error where a generated LOD starts (crowd.asset.lod)
    characters: tuple = ()  # CharacterSpec per character of a mixed crowd; () is one character: model, roles, model_scale above
    # The player drawn as the built-in survivor (crowd.sim.player), after the crowd. Off here, on in scenes (the
    # settings' default): a PipelineConfig is the crowd the library draws, a scene is the game the demo plays.
    survivor: bool = False
    # The built-in town (crowd.asset.town): drawn, and steered around by the crowd. Off here, on in scenes,
    # as the survivor: the benchmarks measure the crowd on the empty plane.
    town: bool = False

    def cast(self) -> tuple[CharacterSpec, ...]:
        """The crowd's characters, in order: ``characters``, or the one that model, roles and model_scale name."""
        return tuple(self.characters) or (CharacterSpec(self.model, 1.0, dict(self.roles), self.model_scale),)
