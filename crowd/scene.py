"""Scenes: what a run uses, in a TOML file the demo loads (``--scene PATH``) and the panel saves back.

A scene names the model, the agent count and seed, the clips it plays (role → clip; only those are
baked), the AI's settings, the features it switches on (weapons, shadows, LOD, culling) and the camera:

    [scene]        name, model ("" = the built-in zombie; relative paths are from the scene's folder),
                   agents, seed
    [clips]        bake_fps (1-240 or "source"), precision ("f32" | "f16"),
                   interpolation ("qt_lerp" | "dq_lerp" | "qt_cubic"), roles = { walk = "shamble", ... },
                   speed = { shamble = 1.2, ... } (playback speed), loop = { attack = true, ... }
    [ai]           any AIConfig field (crowd/ai.py), e.g. runner_share = 0.3
    [features]     weapons, readback_latency (1-3), shadows, culling, lod_distances = [near, far],
                   processor ("auto" | "compute" | "fragment")
    [camera]       eye = [x, y, z], target = [x, y, z], fov_y (degrees); absent: the default view

Every key is optional; a key this module does not know is an error, not something silently ignored.
``load_scene`` raises SceneError with the file, and the line for TOML syntax errors; callers keep the
defaults when it does. ``save_scene`` writes atomically and keeps the previous file as ``<name>.bak``.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomli_w

from .ai import AIConfig, AIError
from .bake import DEFAULT_FPS, SOURCE_RATE
from .gltf_write import atomic_write_bytes
from .pipeline import MAX_AGENTS, PipelineConfig
from .processor import DEFAULT_INTERPOLATION, INTERPOLATIONS
from .render import DEFAULT_LOD_DISTANCES

SCENE_DIR = Path(__file__).resolve().parent.parent / "scenes"
ROLES = ("idle", "walk", "run", "attack", "hit", "death")


class SceneError(ValueError):
    """A scene file that cannot be used; the message is one line and names the file."""


@dataclass
class CameraSetting:
    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    fov_y: float = 45.0


@dataclass
class Scene:
    name: str = "horde"
    model: Path | None = None
    agents: int = 200
    seed: int = 1
    bake_fps: float | str = DEFAULT_FPS  # or "source"
    precision: str = "f32"
    interpolation: str = DEFAULT_INTERPOLATION
    roles: dict = field(default_factory=dict)
    clip_speed: dict = field(default_factory=dict)  # clip name → playback speed
    clip_loop: dict = field(default_factory=dict)  # clip name → loop (true) or play once (false), where set
    ai: AIConfig = field(default_factory=AIConfig)
    weapons: bool = True
    readback_latency: int = 2
    shadows: bool = True
    culling: bool = True
    lod_distances: tuple = DEFAULT_LOD_DISTANCES
    processor: str = "auto"
    camera: CameraSetting | None = None

    def with_overrides(self, source: str = "command line", **values) -> "Scene":
        """A copy with the given settings replaced (None leaves one as it is), validated the same way as
        a file: names are the TOML keys (agents, seed, model, roles, bake_fps, precision, processor,
        shadows, culling, weapons, readback_latency). Roles are merged into the scene's."""
        data = scene_to_dict(self)
        tables = {key: table for table, keys in _SCHEMA.items() for key in keys}
        for key, value in values.items():
            if value is None:
                continue
            if key not in tables:
                raise SceneError(f"{source}: unknown scene setting {key!r}")
            if key == "model":
                value = str(Path(value).resolve())
            elif key == "roles":
                value = {**data["clips"]["roles"], **value}
            elif key == "lod_distances":
                value = list(value)
            data[tables[key]][key] = value
        try:
            return scene_from_dict(data, None, source)
        except SceneError as exc:
            # Name the flag the user typed: "command line: scene.agents must ..." → "--agents must ...".
            message = str(exc)
            for key, table in tables.items():
                message = message.replace(f"{source}: {table}.{key}", "--" + key.replace("_", "-"))
            raise SceneError(message) from None

    def camera_for(self, aspect: float):
        """The scene's camera as a render Camera, or None for the pipeline's default view."""
        from .render import Camera

        if self.camera is None:
            return None
        return Camera(eye=np.array(self.camera.eye, np.float64), target=np.array(self.camera.target, np.float64),
                      fov_y=self.camera.fov_y, aspect=aspect)

    def pipeline_config(self) -> PipelineConfig:
        return PipelineConfig(agents=self.agents, seed=self.seed, model=self.model, roles=dict(self.roles), bake_fps=self.bake_fps,
                              precision=self.precision, interpolation=self.interpolation, processor_path=self.processor, shadows=self.shadows, culling=self.culling,
                              lod_distances=tuple(self.lod_distances), ai=self.ai, weapons=self.weapons,
                              readback_latency=self.readback_latency)


# table → key → kind (int, float, bool, str, roles, pair, vec3, path); [ai] takes the AIConfig fields
_SCHEMA = {
    "scene": {"name": "str", "model": "path", "agents": "int", "seed": "int"},
    "clips": {"bake_fps": "rate", "precision": "str", "interpolation": "str", "roles": "roles", "speed": "speeds", "loop": "loops"},
    "features": {"weapons": "bool", "readback_latency": "int", "shadows": "bool", "culling": "bool", "lod_distances": "pair",
                 "processor": "str"},
    "camera": {"eye": "vec3", "target": "vec3", "fov_y": "float"},
}


def _typed(where: str, kind: str, value):
    """The value as `kind`, or SceneError naming `where`."""
    def bad(what):
        return SceneError(f"{where} must be {what}, got {value!r}")

    if kind == "bool":
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("a whole number")
        return value
    if kind == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise bad("a finite number")
        return float(value)
    if kind == "rate":  # a bake rate
        if value == SOURCE_RATE:
            return value
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 1.0 <= value <= 240.0:
            raise bad(f"1 to 240 (fps) or \"{SOURCE_RATE}\"")
        return float(value)
    if kind in ("str", "path"):
        if not isinstance(value, str):
            raise bad("a string")
        return value
    if kind in ("pair", "vec3"):
        n = 2 if kind == "pair" else 3
        if not isinstance(value, list) or len(value) != n:
            raise bad(f"a list of {n} numbers")
        return tuple(_typed(where, "float", v) for v in value)
    if kind in ("speeds", "loops"):
        if not isinstance(value, dict):
            raise bad("a table of clip name = value")
        for clip, v in value.items():
            if kind == "loops" and not isinstance(v, bool):
                raise SceneError(f"{where}.{clip} must be true or false, got {v!r}")
            if kind == "speeds" and (isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.05 <= v <= 20.0):
                raise SceneError(f"{where}.{clip} must be a playback speed of 0.05 to 20, got {v!r}")
        return {k: (float(v) if kind == "speeds" else v) for k, v in value.items()}
    if kind == "roles":
        if not isinstance(value, dict):
            raise bad("a table of role = clip name")
        for role, clip in value.items():
            if role not in ROLES:
                raise SceneError(f"{where}: unknown role {role!r} (roles are {', '.join(ROLES)})")
            if not isinstance(clip, str) or not clip:
                raise SceneError(f"{where}.{role} must be a clip name, got {clip!r}")
        return dict(value)
    raise AssertionError(kind)


def scene_from_dict(data: dict, base: Path | None = None, source: str = "scene") -> Scene:
    """A validated Scene from parsed TOML. Relative model paths are resolved against `base`."""
    scene = Scene()
    ai_fields = {f.name: f for f in dataclasses.fields(AIConfig)}
    for table, values in data.items():
        if table != "ai" and table not in _SCHEMA:
            raise SceneError(f"{source}: unknown table [{table}] (tables are {', '.join(['ai', *_SCHEMA])})")
        if not isinstance(values, dict):
            raise SceneError(f"{source}: {table} must be a table")
        known = ai_fields if table == "ai" else _SCHEMA[table]
        for key in values:
            if key not in known:
                raise SceneError(f"{source}: unknown key {key!r} in [{table}] (known: {', '.join(known)})")
    s = data.get("scene", {})
    where = lambda table, key: f"{source}: {table}.{key}"
    if "name" in s:
        scene.name = _typed(where("scene", "name"), "str", s["name"])
    if s.get("model"):
        model = Path(_typed(where("scene", "model"), "path", s["model"]))
        scene.model = model if model.is_absolute() or base is None else (base / model)
    if "agents" in s:
        scene.agents = _typed(where("scene", "agents"), "int", s["agents"])
        if not 0 <= scene.agents <= MAX_AGENTS:
            raise SceneError(f"{where('scene', 'agents')} must be 0 to {MAX_AGENTS}, got {scene.agents}")
    if "seed" in s:
        scene.seed = _typed(where("scene", "seed"), "int", s["seed"])
    c = data.get("clips", {})
    if "bake_fps" in c:
        scene.bake_fps = _typed(where("clips", "bake_fps"), "rate", c["bake_fps"])
    if "precision" in c:
        scene.precision = _typed(where("clips", "precision"), "str", c["precision"])
        if scene.precision not in ("f32", "f16"):
            raise SceneError(f"{where('clips', 'precision')} must be \"f32\" or \"f16\", got {scene.precision!r}")
    if "interpolation" in c:
        scene.interpolation = _typed(where("clips", "interpolation"), "str", c["interpolation"])
        if scene.interpolation not in INTERPOLATIONS:
            raise SceneError(f"{where('clips', 'interpolation')} must be one of {', '.join(INTERPOLATIONS)}, got {scene.interpolation!r}")
    if "roles" in c:
        scene.roles = _typed(where("clips", "roles"), "roles", c["roles"])
    if "speed" in c:
        scene.clip_speed = _typed(where("clips", "speed"), "speeds", c["speed"])
    if "loop" in c:
        scene.clip_loop = _typed(where("clips", "loop"), "loops", c["loop"])
    f = data.get("features", {})
    for key in ("weapons", "shadows", "culling"):
        if key in f:
            setattr(scene, key, _typed(where("features", key), "bool", f[key]))
    if "readback_latency" in f:
        scene.readback_latency = _typed(where("features", "readback_latency"), "int", f["readback_latency"])
        if not 1 <= scene.readback_latency <= 3:
            raise SceneError(f"{where('features', 'readback_latency')} must be 1 to 3, got {scene.readback_latency}")
    if "lod_distances" in f:
        near, far = _typed(where("features", "lod_distances"), "pair", f["lod_distances"])
        if not 0 < near <= far:
            raise SceneError(f"{where('features', 'lod_distances')} must be two increasing positive distances")
        scene.lod_distances = (near, far)
    if "processor" in f:
        scene.processor = _typed(where("features", "processor"), "str", f["processor"])
        if scene.processor not in ("auto", "compute", "fragment"):
            raise SceneError(f"{where('features', 'processor')} must be auto, compute or fragment, got {scene.processor!r}")
    if "ai" in data:
        values = {}
        for key, value in data["ai"].items():
            kind = "int" if key == "health" else "float"
            values[key] = _typed(where("ai", key), kind, value)
        try:
            scene.ai = AIConfig(**values).validate()
        except AIError as exc:
            raise SceneError(f"{source}: [ai] {exc}") from None
    if "camera" in data:
        cam = data["camera"]
        if "eye" not in cam or "target" not in cam:
            raise SceneError(f"{source}: [camera] needs both eye and target")
        eye = _typed(where("camera", "eye"), "vec3", cam["eye"])
        target = _typed(where("camera", "target"), "vec3", cam["target"])
        fov = _typed(where("camera", "fov_y"), "float", cam.get("fov_y", 45.0))
        if math.dist(eye, target) < 1e-6 or not 1.0 <= fov <= 170.0:
            raise SceneError(f"{source}: [camera] needs eye apart from target and fov_y of 1 to 170 degrees")
        scene.camera = CameraSetting(eye, target, fov)
    return scene


def load_scene(path) -> Scene:
    """Read and validate a scene file; SceneError (one line, naming the file) when it cannot be used."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"{path}: cannot read it ({exc.__class__.__name__}: {exc})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{path}: not valid TOML: {exc}") from None
    return scene_from_dict(data, path.resolve().parent, str(path))


def scene_to_dict(scene: Scene, base: Path | None = None) -> dict:
    """The TOML tables of a scene; AI settings are written only where they differ from the defaults."""
    model = ""
    if scene.model is not None:
        model = str(scene.model)
        if base is not None:
            try:
                model = str(Path(scene.model).resolve().relative_to(base.resolve()))
            except ValueError:
                model = str(Path(scene.model).resolve())
    default_ai = AIConfig()
    out = {
        "scene": {"name": scene.name, "model": model, "agents": scene.agents, "seed": scene.seed},
        "clips": {"bake_fps": scene.bake_fps, "precision": scene.precision, "interpolation": scene.interpolation, "roles": dict(scene.roles),
                  "speed": dict(scene.clip_speed), "loop": dict(scene.clip_loop)},
        "features": {"weapons": scene.weapons, "readback_latency": scene.readback_latency, "shadows": scene.shadows,
                     "culling": scene.culling, "lod_distances": list(scene.lod_distances), "processor": scene.processor},
        "ai": {f.name: getattr(scene.ai, f.name) for f in dataclasses.fields(AIConfig)
               if getattr(scene.ai, f.name) != getattr(default_ai, f.name)},
    }
    if scene.camera is not None:
        out["camera"] = {"eye": list(scene.camera.eye), "target": list(scene.camera.target), "fov_y": scene.camera.fov_y}
    return out


def save_scene(scene: Scene, path) -> Path | None:
    """Write the scene atomically: the file is either the old one or the whole new one, never half of
    either. An existing file is first copied to ``<name>.bak`` (also atomically). Returns the backup's
    path, or None when there was no previous file."""
    path = Path(path)
    data = tomli_w.dumps(scene_to_dict(scene, path.resolve().parent)).encode()
    scene_from_dict(tomllib.loads(data.decode()), path.resolve().parent, str(path))  # what we write must load back
    backup = None
    if path.exists():
        backup = path.with_name(path.name + ".bak")
        atomic_write_bytes(backup, path.read_bytes())
    atomic_write_bytes(path, data)
    return backup
