"""Scenes: what a run uses, in a TOML file the demo loads (``--scene PATH``) and the panel saves back.

A scene names its characters (a model each, its share of the crowd and the clips it plays: role → clip;
only those are baked), the agent count and seed, the AI's settings, the features it switches on
(weapons, shadows, LOD, culling) and the camera:

    [scene]        name, model ("" = the built-in zombie, "brute" the built-in brute, else a glTF file;
                   relative paths are from the scene's folder), and the ``scene`` settings (agents, seed)
    [clips]        the ``clips`` settings (bake_fps, precision, compression_bound_mm, interpolation), and
                   roles = { walk = "shamble", ... }, speed = { shamble = 1.2, ... } (playback speed),
                   loop = { attack = true, ... }
    [[characters]] a crowd of several characters, one table each: model, share (relative: 3 and 1 make
                   a quarter of the crowd the second's), and its own roles, speed, loop, model_scale and
                   morph = { belly_swell = [0.0, 0.9], ... } (each agent's offset of a morph target lies in
                   [lo, hi], fixed for the agent); with these, [scene] names no model and [clips] no roles,
                   speeds or loops
    [features]     the ``features`` settings (weapons, readback_latency, shadows, culling, occlusion,
                   lod_distances = [d1, d2, d3], processor, cull)
    [ai]           the ``ai`` settings (crowd.sim.config.AIConfig), e.g. runner_share = 0.3
    [camera]       eye = [x, y, z], target = [x, y, z], fov_y (degrees); absent: the default view

The settings, their bounds and defaults are crowd.settings' (declared once, for the command line and
the panel too); this module adds the tables that are not single values (roles, speeds, loops, camera).

Every key is optional (a file naming neither a model nor characters plays the default cast: zombies and
brutes, three to one); a key this module does not know is an error, not something silently ignored.
``load_scene`` raises SceneError with the file, and the line for TOML syntax errors; callers keep the
defaults when it does. ``save_scene`` writes atomically and keeps the previous file as ``<name>.bak``.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomli_w

from .errors import CrowdError
from .anim.roles import ROLES
from .files import atomic_write_bytes
from .frame import MAX_CAST, Camera
from .asset.gltf import is_built_in
from .pipeline_config import CharacterSpec, PipelineConfig
from .settings import DEFAULTS, SCENE_GROUPS, SETTINGS, group
from .sim.config import AIConfig, AIError


class SceneError(CrowdError, ValueError):
    """A scene file that cannot be used; the message is one line and names the file."""


@dataclass
class CameraSetting:
    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    fov_y: float = 45.0


@dataclass(frozen=True)
class CharacterEntry:
    """One character of a scene's cast: its model (a built-in's name: "zombie", "brute"; or a glTF file), its share of the crowd, its roles, its clips' playback speeds and loops, its size factor."""

    model: Path | str = "zombie"
    share: float = 1.0
    roles: dict = field(default_factory=dict)
    clip_speed: dict = field(default_factory=dict)  # clip name → playback speed
    clip_loop: dict = field(default_factory=dict)  # clip name → loop (true) or play once (false), where set
    model_scale: float | str = DEFAULTS["model_scale"]
    morph: dict = field(default_factory=dict)  # morph target → (lo, hi): each agent's body variation (crowd.anim.morph)
    clips: tuple = ()  # glTF files whose clips join the model's, matched to its joints by name (crowd.asset.gltf.library)

    def spec(self) -> CharacterSpec:
        return CharacterSpec(self.model, self.share, dict(self.roles), self.model_scale, dict(self.morph), tuple(self.clips))


# What a fresh clone shows: a mixed horde of the two built-in zombie types, three zombies to a brute, each
# zombie's body its own (the built-ins' morph targets, crowd.asset.morph_targets.MORPH_TARGETS).
BODY_VARIATION = {"belly_swell": (0.0, 0.9), "chest_sunken": (0.0, 1.0), "gaunt": (0.0, 1.0)}
DEFAULT_CAST = (CharacterEntry("zombie", 3.0, morph=BODY_VARIATION), CharacterEntry("brute", 1.0, morph=BODY_VARIATION))


@dataclass
class Scene:
    name: str = "horde"
    characters: tuple = DEFAULT_CAST  # CharacterEntry per character, in the cast's order
    agents: int = DEFAULTS["agents"]
    seed: int = DEFAULTS["seed"]
    bake_fps: float | str = DEFAULTS["bake_fps"]  # or "source"
    precision: str = DEFAULTS["precision"]
    compression_bound_mm: float = DEFAULTS["compression_bound_mm"]
    interpolation: str = DEFAULTS["interpolation"]
    ai: AIConfig = field(default_factory=AIConfig)
    weapons: bool = DEFAULTS["weapons"]
    readback_latency: int = DEFAULTS["readback_latency"]
    shadows: bool = DEFAULTS["shadows"]
    culling: bool = DEFAULTS["culling"]
    occlusion: bool = DEFAULTS["occlusion"]
    lod_distances: tuple = DEFAULTS["lod_distances"]
    lod_error_px: float = DEFAULTS["lod_error_px"]
    processor: str = DEFAULTS["processor"]
    ai_path: str = DEFAULTS["ai_path"]
    cull: str = DEFAULTS["cull"]
    gl: str = DEFAULTS["gl"]
    foot_lock: bool = DEFAULTS["foot_lock"]
    morphs: bool = DEFAULTS["morphs"]
    impostors: str = DEFAULTS["impostors"]
    lod_fade: float = DEFAULTS["lod_fade"]
    impostor_distance: float = DEFAULTS["impostor_distance"]
    survivor: bool = DEFAULTS["survivor"]
    town: bool = DEFAULTS["town"]
    camera: CameraSetting | None = None

    # The first character's (the only one's in a scene of one character).
    @property
    def model(self):
        return self.characters[0].model

    @property
    def roles(self) -> dict:
        return self.characters[0].roles

    @property
    def clip_speed(self) -> dict:
        return self.characters[0].clip_speed

    @property
    def clip_loop(self) -> dict:
        return self.characters[0].clip_loop

    @property
    def model_scale(self):
        return self.characters[0].model_scale

    def with_overrides(self, source: str = "command line", **values) -> "Scene":
        """A copy with the given settings replaced (None leaves one as it is), each checked as a file's
        would be, an error naming its command-line flag ("--agents: ..."): names are the TOML keys (agents, seed, model,
        roles, bake_fps, precision, processor, shadows, culling, occlusion, weapons, readback_latency, lod_distances,
        and the AI's), and characters (a list of (model, share) pairs: the cast). A model makes the cast that one
        character; roles and model_scale are the one character's, merged into its own."""
        data = scene_to_dict(self)
        if values.get("characters") is not None:
            data.pop("characters", None)
            data["scene"].pop("model", None)
            data["characters"] = [_cast_entry(model, share, source) for model, share in values["characters"]]
        if values.get("model") is not None:
            data.pop("characters", None)
            for key in ("roles", "speed", "loop", "files"):
                data["clips"].pop(key, None)
        for key, value in values.items():
            if value is None or key == "characters":
                continue
            table = _TABLE_OF.get(key)
            if table is None:
                raise SceneError(f"{source}: unknown scene setting {key!r}")
            if key in SETTINGS:
                value = _toml_value(SETTINGS[key].check(value, SceneError, SETTINGS[key].flag))
            if key == "files":  # clip libraries: files, resolved where they were named
                value = [str(Path(v).resolve()) for v in value]
            if key in ("roles", "model_scale", "files") and "characters" in data:
                if len(data["characters"]) > 1:
                    raise SceneError(f"{source}: {key} belongs to one character, and this scene has {len(data['characters'])}: "
                                     f"set it per character in the scene's [[characters]]")
                entry = data["characters"][0]
                entry["clips" if key == "files" else key] = {**entry.get(key, {}), **value} if key == "roles" else value
                continue
            if key == "model":
                value = value if is_built_in(str(value)) else str(Path(value).resolve())
            elif key == "roles":
                value = {**data["clips"].get("roles", {}), **value}
            data.setdefault(table, {})[key] = value
        return scene_from_dict(data, None, source)

    def camera_for(self, aspect: float) -> Camera | None:
        """The scene's camera, or None for the pipeline's default view."""
        if self.camera is None:
            return None
        return Camera(eye=np.array(self.camera.eye, np.float64), target=np.array(self.camera.target, np.float64),
                      fov_y=self.camera.fov_y, aspect=aspect)

    def pipeline_config(self) -> PipelineConfig:
        return PipelineConfig(agents=self.agents, seed=self.seed, characters=tuple(c.spec() for c in self.characters), bake_fps=self.bake_fps,
                              precision=self.precision, compression_bound_mm=self.compression_bound_mm, interpolation=self.interpolation, processor_path=self.processor, ai_path=self.ai_path, shadows=self.shadows, culling=self.culling,
                              occlusion=self.occlusion, lod_distances=tuple(self.lod_distances), lod_error_px=self.lod_error_px, ai=self.ai, weapons=self.weapons,
                              readback_latency=self.readback_latency, cull=self.cull, gl=self.gl, foot_lock=self.foot_lock, morphs=self.morphs,
                              impostors=self.impostors, impostor_distance=self.impostor_distance, lod_fade=self.lod_fade, survivor=self.survivor, town=self.town)


# The keys of each table: the settings of its group, and the few structured keys only scenes have.
_EXTRA_KEYS = {"scene": ("name", "model"), "clips": ("roles", "speed", "loop", "files"), "features": (), "ai": ()}
_KEYS = {table: (*_EXTRA_KEYS[table], *group(table)) for table in SCENE_GROUPS}
_KEYS["camera"] = ("eye", "target", "fov_y")
_TABLE_OF = {key: table for table, keys in _KEYS.items() if table != "camera" for key in keys}
_CHARACTER_KEYS = ("model", "share", "roles", "speed", "loop", "model_scale", "morph", "clips")  # one [[characters]] table
MAX_SHARE = 1e6  # shares are relative; this bounds a typo's reach


def _cast_entry(model, share, source: str) -> dict:
    """A [[characters]] table from a command line's (model, share): a built-in's name, or a file (resolved)."""
    model = str(model)
    return {"model": model if is_built_in(model) or not model else str(Path(model).resolve()), "share": share}


def _share(where: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or not 0 < value <= MAX_SHARE:
        raise SceneError(f"{where} must be a number above 0, at most {MAX_SHARE:g} (shares are relative), got {value!r}")
    return float(value)


def _model(where: str, value, base: Path | None):
    """A model as a scene names it: "" or "zombie" (the built-in zombie), a built-in's name, or a file,
    relative to `base` (the scene's folder)."""
    name = _string(where, value)
    if not name or name == "zombie":
        return "zombie"
    if is_built_in(name):
        return name
    model = Path(name)
    return model if model.is_absolute() or base is None else (base / model)


def _files(where: str, value, base: Path | None) -> tuple:
    """A list of glTF files (clip libraries), each relative to `base` (the scene's folder) unless absolute."""
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise SceneError(f"{where} must be a list of glTF files, got {value!r}")
    return tuple(Path(v) if Path(v).is_absolute() or base is None else base / v for v in value)


def _toml_value(value):
    return list(value) if isinstance(value, tuple) else value


def _string(where: str, value) -> str:
    if not isinstance(value, str):
        raise SceneError(f"{where} must be a string, got {value!r}")
    return value


def _vec3(where: str, value) -> tuple[float, float, float]:
    if not isinstance(value, list) or len(value) != 3 or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value):
        raise SceneError(f"{where} must be a list of 3 finite numbers, got {value!r}")
    return tuple(float(v) for v in value)


def _clip_table(where: str, value, setting) -> dict:
    """A table of clip name = value, each checked by `setting` (playback speed, or loop on/off)."""
    if not isinstance(value, dict):
        raise SceneError(f"{where} must be a table of clip name = value, got {value!r}")
    return {clip: setting.check(v, SceneError, f"{where}.{clip}") for clip, v in value.items()}


def _morph(where: str, value) -> dict:
    """A table of morph target = [lo, hi]: each agent's offset of that target lies in it (both ends checked
    by the morph_weight setting, lo <= hi); the model is checked for the names when the crowd is built."""
    if not isinstance(value, dict):
        raise SceneError(f"{where} must be a table of morph target = [lo, hi], got {value!r}")
    out = {}
    for name, pair in value.items():
        if not isinstance(pair, list) or len(pair) != 2:
            raise SceneError(f"{where}.{name} must be [lo, hi], got {pair!r}")
        lo, hi = (SETTINGS["morph_weight"].check(v, SceneError, f"{where}.{name}") for v in pair)
        if lo > hi:
            raise SceneError(f"{where}.{name}: lo {lo:g} is above hi {hi:g}")
        out[str(name)] = (lo, hi)
    return out


def _roles(where: str, value) -> dict:
    if not isinstance(value, dict):
        raise SceneError(f"{where} must be a table of role = clip name, got {value!r}")
    for role, clip in value.items():
        if role not in ROLES:
            raise SceneError(f"{where}: unknown role {role!r} (roles are {', '.join(ROLES)})")
        if not isinstance(clip, str) or not clip:
            raise SceneError(f"{where}.{role} must be a clip name, got {clip!r}")
    return dict(value)


def scene_from_dict(data: dict, base: Path | None = None, source: str = "scene") -> Scene:
    """A validated Scene from parsed TOML. Relative model paths are resolved against `base`."""
    scene = Scene()
    for table, values in data.items():
        if table == "characters":
            continue
        if table not in _KEYS:
            raise SceneError(f"{source}: unknown table [{table}] (tables are {', '.join(_KEYS)}, and [[characters]])")
        if not isinstance(values, dict):
            raise SceneError(f"{source}: {table} must be a table")
        for key in values:
            if key not in _KEYS[table]:
                raise SceneError(f"{source}: unknown key {key!r} in [{table}] (known: {', '.join(_KEYS[table])})")
    where = lambda table, key: f"{source}: {table}.{key}"
    ai = {}
    scale = None
    for table in SCENE_GROUPS:
        for key, setting in group(table).items():
            if key in data.get(table, {}):
                value = setting.check(data[table][key], SceneError, where(table, key))
                if table == "ai":
                    ai[key] = value
                elif key == "model_scale":
                    scale = value
                else:
                    setattr(scene, key, value)
    s, c = data.get("scene", {}), data.get("clips", {})
    if "name" in s:
        scene.name = _string(where("scene", "name"), s["name"])
    if "characters" in data:
        own = [key for key in ("model", "model_scale") if key in s] + [key for key in ("roles", "speed", "loop", "files") if c.get(key)]
        if own:
            raise SceneError(f"{source}: with [[characters]], each character has its own model, roles, speed, loop and model_scale; "
                             f"[scene]/[clips] give {', '.join(own)}")
        scene.characters = _characters(data["characters"], base, source)
    elif "model" in s or scale is not None or any(key in c for key in ("roles", "speed", "loop", "files")):
        # One character: the model (the zombie when none is named), its roles, speeds, loops and size.
        scene.characters = (CharacterEntry(
            _model(where("scene", "model"), s.get("model", ""), base), 1.0,
            _roles(where("clips", "roles"), c["roles"]) if "roles" in c else {},
            _clip_table(where("clips", "speed"), c["speed"], SETTINGS["clip_speed"]) if "speed" in c else {},
            _clip_table(where("clips", "loop"), c["loop"], SETTINGS["clip_loop"]) if "loop" in c else {},
            DEFAULTS["model_scale"] if scale is None else scale, {},
            _files(where("clips", "files"), c["files"], base) if "files" in c else ()),)
    if ai:
        try:
            scene.ai = AIConfig(**ai).validate()  # the relations between AI settings (min <= max, ...)
        except AIError as exc:
            raise SceneError(f"{source}: [ai] {exc}") from None
    if "camera" in data:
        cam = data["camera"]
        if "eye" not in cam or "target" not in cam:
            raise SceneError(f"{source}: [camera] needs both eye and target")
        eye = _vec3(where("camera", "eye"), cam["eye"])
        target = _vec3(where("camera", "target"), cam["target"])
        fov = cam.get("fov_y", 45.0)
        if isinstance(fov, bool) or not isinstance(fov, (int, float)) or math.dist(eye, target) < 1e-6 or not 1.0 <= fov <= 170.0:
            raise SceneError(f"{source}: [camera] needs eye apart from target and fov_y of 1 to 170 degrees")
        scene.camera = CameraSetting(eye, target, float(fov))
    return scene


def _characters(value, base: Path | None, source: str) -> tuple[CharacterEntry, ...]:
    """The [[characters]] array of tables, each checked, naming its index in errors."""
    if not isinstance(value, list) or not value or not all(isinstance(v, dict) for v in value):
        raise SceneError(f"{source}: characters must be an array of tables ([[characters]]), one per character")
    if len(value) > MAX_CAST:
        raise SceneError(f"{source}: {len(value)} characters; a crowd has at most {MAX_CAST}")
    out = []
    for k, entry in enumerate(value):
        at = f"{source}: characters[{k}]"
        for key in entry:
            if key not in _CHARACTER_KEYS:
                raise SceneError(f"{at}: unknown key {key!r} (known: {', '.join(_CHARACTER_KEYS)})")
        out.append(CharacterEntry(
            _model(f"{at}.model", entry.get("model", ""), base), _share(f"{at}.share", entry.get("share", 1.0)),
            _roles(f"{at}.roles", entry["roles"]) if "roles" in entry else {},
            _clip_table(f"{at}.speed", entry["speed"], SETTINGS["clip_speed"]) if "speed" in entry else {},
            _clip_table(f"{at}.loop", entry["loop"], SETTINGS["clip_loop"]) if "loop" in entry else {},
            SETTINGS["model_scale"].check(entry["model_scale"], SceneError, f"{at}.model_scale") if "model_scale" in entry else DEFAULTS["model_scale"],
            _morph(f"{at}.morph", entry["morph"]) if "morph" in entry else {},
            _files(f"{at}.clips", entry["clips"], base) if "clips" in entry else ()))
    return tuple(out)


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


def _model_text(model, base: Path | None) -> str:
    """A model as a scene file writes it: a built-in's name, or a path (relative to `base` where it can be)."""
    if model is None or model == "zombie":
        return ""
    if is_built_in(model):
        return model
    if base is not None:
        try:
            return str(Path(model).resolve().relative_to(base.resolve()))
        except ValueError:
            pass
    return str(Path(model).resolve())


def scene_to_dict(scene: Scene, base: Path | None = None) -> dict:
    """The TOML tables of a scene; AI settings are written only where they differ from the defaults. A
    scene of one character names it in [scene] and [clips]; a cast, in [[characters]]."""
    out = {table: {key: _toml_value(getattr(scene, key)) for key in group(table) if key != "model_scale"} for table in ("scene", "clips", "features")}
    out["scene"] = {"name": scene.name, **out["scene"]}
    if len(scene.characters) == 1:
        one = scene.characters[0]
        out["scene"].update(model=_model_text(one.model, base), model_scale=_toml_value(one.model_scale))
        out["clips"].update(roles=dict(one.roles), speed=dict(one.clip_speed), loop=dict(one.clip_loop))
        if one.clips:
            out["clips"]["files"] = [_model_text(p, base) for p in one.clips]
    else:
        out["characters"] = [{"model": _model_text(c.model, base) or "zombie", "share": c.share, "roles": dict(c.roles),
                              "speed": dict(c.clip_speed), "loop": dict(c.clip_loop), "model_scale": _toml_value(c.model_scale),
                              "morph": {name: list(pair) for name, pair in c.morph.items()},
                              **({"clips": [_model_text(p, base) for p in c.clips]} if c.clips else {})}
                             for c in scene.characters]
    out["ai"] = {key: getattr(scene.ai, key) for key, setting in group("ai").items() if getattr(scene.ai, key) != setting.default}
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
