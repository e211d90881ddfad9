"""Every value a person can set, declared once: its type, bounds, default and one line of help.

The command line (``crowd-demo``'s flags), the scene files (their TOML keys and checks), the panel
(its widget ranges) and the stages (their own input checks) all read this table, so a bound is
written here and nowhere else. A value is checked by ``SETTINGS[name].check(value, error, source)``,
which raises ``error`` with the same one-line reason everywhere ("agent count must be a whole number
from 0 to 1000000, got -1"), prefixed by where the value came from when the caller says.

This module sits below every stage and imports none of them.

Groups, which are also the scene file's tables: ``scene`` (what runs), ``clips`` (the bake),
``features`` (what is drawn), ``ai`` (the crowd's behaviour, ``crowd.sim.config.AIConfig``), ``session``
(live controls of a running crowd: not in scene files) and ``run`` (command-line only: how long, how big).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np
from .errors import CrowdError

SOURCE_RATE = "source"  # bake each clip at its own key rate
AUTO_SCALE = "auto"  # measure the character's standing height and scale it to a person's where it is far off
INF = math.inf


class SettingError(CrowdError, ValueError):
    """A value a setting cannot take; the message is one line."""


@dataclass(frozen=True)
class Setting:
    name: str  # the scene file's key and the command line's --flag (with dashes)
    group: str
    kind: str  # int, float, bool, choice, rate (fps or "source"), scale (a factor or "auto"), size (WxH),
    #            ascending (as many numbers as the default, each no larger than the next)
    default: object
    help: str
    label: str = ""  # the words an error uses ("agent count"); the name when empty
    low: float = -INF
    high: float = INF
    open_low: bool = False  # low itself is refused (> low, not >= low)
    choices: tuple = ()
    slider: tuple | None = None  # the panel's widget range, inside the bounds

    @property
    def words(self) -> str:
        return self.label or self.name

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    def rule(self) -> str:
        """What the setting accepts, in words."""
        if self.kind == "bool":
            return "true or false"
        if self.kind == "choice":
            return "one of " + ", ".join(self.choices)
        if self.kind == "rate":
            return f"{_num(self.low)} to {_num(self.high)} fps or {SOURCE_RATE!r}"
        if self.kind == "scale":
            return f"a factor from {self.low:g} to {self.high:g} or {AUTO_SCALE!r}"
        if self.kind == "ascending":
            count = {2: "two", 3: "three", 4: "four"}.get(len(self.default), str(len(self.default)))
            return f"{count} numbers above {_num(self.low)}, each no larger than the next"
        if self.kind == "size":
            return f"WxH with each side {_num(self.low)} to {_num(self.high)}"
        noun = "a whole number" if self.kind == "int" else "a number"
        lo, hi = self.low, self.high
        if lo > -INF and hi < INF:
            return f"{noun} from {_num(lo)} to {_num(hi)}" if not self.open_low else f"{noun} above {_num(lo)}, at most {_num(hi)}"
        if lo > -INF:
            return f"{noun} above {_num(lo)}" if self.open_low else f"{noun} of at least {_num(lo)}"
        if hi < INF:
            return f"{noun} of at most {_num(hi)}"
        return "a whole number" if self.kind == "int" else "a finite number"

    def reason(self, value) -> str:
        shown = repr(list(value)) if isinstance(value, (list, tuple)) else repr(value)  # a TOML array and a flag's list alike
        if len(shown) > 40:  # a 400-digit number stays a readable line
            shown = f"{shown[:24]}... ({len(shown)} characters)"
        return f"{self.words} must be {self.rule()}, got {shown}"

    def check(self, value, error: type[Exception] = SettingError, source: str | None = None, shown=None):
        """`value` as this setting's type (ints stay ints, floats become float, ascending lists tuples), or
        `error` raised with the one-line reason, after "source: " when a source is given. The reason
        names `shown` instead of the value when given (the text a person typed)."""
        ok = self._checked(value)
        if ok is _BAD:
            reason = self.reason(value if shown is None else shown)
            raise error(reason if source is None else f"{source}: {reason}")
        return ok

    def _checked(self, value):
        k = self.kind
        if k == "bool":
            return bool(value) if isinstance(value, (bool, np.bool_)) else _BAD
        if k == "choice":
            return value if isinstance(value, str) and value in self.choices else _BAD
        if k == "rate":
            return value if value == SOURCE_RATE else self._number(value, float)
        if k == "scale":
            return value if value == AUTO_SCALE else self._number(value, float)
        if k == "ascending":
            if not isinstance(value, (list, tuple)) or len(value) != len(self.default):
                return _BAD
            numbers_ = tuple(_real(v) for v in value)
            if _BAD in numbers_ or not self._above_low(numbers_[0]) or numbers_[-1] > self.high:
                return _BAD
            return numbers_ if all(a <= b for a, b in zip(numbers_, numbers_[1:])) else _BAD
        if k == "size":
            if not isinstance(value, (list, tuple)) or len(value) != 2 or not all(_whole(v) for v in value):
                return _BAD
            return tuple(int(v) for v in value) if all(self.low <= v <= self.high for v in value) else _BAD
        return self._number(value, int if k == "int" else float)

    def _above_low(self, v: float) -> bool:
        return v > self.low if self.open_low else v >= self.low

    def _number(self, value, cast):
        if cast is int:
            if not _whole(value):
                return _BAD
        else:
            value = _real(value)
            if value is _BAD:
                return _BAD
        if not self._above_low(value) or value > self.high:
            return _BAD
        return cast(value)

    def from_text(self, text: str):
        """A command-line string as this setting's type (unchecked), or the string itself when it is
        not one, so that ``check`` names it in its reason."""
        t = text.strip()
        try:
            if self.kind == "int":
                return int(t)
            if self.kind == "float":
                return _number_text(t)
            if self.kind == "rate":
                return t if t == SOURCE_RATE else _number_text(t)
            if self.kind == "scale":
                return t if t == AUTO_SCALE else _number_text(t)
            if self.kind == "bool":
                return {"true": True, "on": True, "1": True, "false": False, "off": False, "0": False}.get(t.lower(), text)
            if self.kind == "ascending":
                return tuple(_number_text(v) for v in t.split(","))
            if self.kind == "size":
                w, sep, h = t.lower().partition("x")
                return (int(w), int(h)) if sep else text
        except ValueError:
            return text
        return t


_BAD = object()


def _number_text(text: str) -> int | float:
    """"3" as 3 and "3.0" as 3.0, as TOML reads them, so a flag and a file show a value the same way."""
    try:
        return int(text)
    except ValueError:
        return float(text)


def _whole(v) -> bool:
    """An int (numpy's too), not a bool."""
    return isinstance(v, numbers.Integral) and not isinstance(v, bool)


def _real(v):
    """A finite float, or _BAD for anything else (bools and strings included)."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        return _BAD
    try:
        v = float(v)
    except OverflowError:  # an int past float's range (TOML and int() take any size)
        return _BAD
    return v if math.isfinite(v) else _BAD


def _num(v: float) -> str:
    return f"{v:g}" if isinstance(v, float) and v != int(v) else str(int(v))


def _ai(name, default, help, kind="float", **bounds) -> Setting:
    return Setting(name, "ai", kind, default, help, label=f"AI setting {name}", **bounds)


_ALL = (
    # what runs
    Setting("agents", "scene", "int", 200, "number of zombies", label="agent count", low=0, high=1_000_000, slider=(0, 10_000)),
    Setting("seed", "scene", "int", 1, "random seed of the crowd (the same seed gives the same crowd)", low=0, high=2**63 - 1),
    Setting("model_scale", "scene", "scale", AUTO_SCALE,
            f'the model\'s size factor; "{AUTO_SCALE}" scales a character standing outside 0.5 to 3 m to 1.8 m',
            label="model scale", low=1e-6, high=1e6),
    # the bake
    Setting("bake_fps", "clips", "rate", 30.0, f'bake rate in frames per second, or "{SOURCE_RATE}": each clip at its own key rate',
            label="bake rate", low=1, high=240, slider=(5, 60)),
    Setting("precision", "clips", "choice", "f32",
            "storage of the animation texture: f32, f16, or compressed (each track quantised to its own range, within compression_bound_mm)",
            choices=("f32", "f16", "compressed")),
    Setting("compression_bound_mm", "clips", "float", 0.5,
            "millimetres: the largest error the compressed bake may add at any key (ACL's 3 cm shell); only with precision compressed",
            label="compression bound", low=0.001, high=100, slider=(0.01, 2.0)),
    Setting("interpolation", "clips", "choice", "qt_corrected",
            "how keys are sampled and layers blended (docs/BENCHMARKS.md says why the default is the default)",
            choices=("dq_lerp", "qt_lerp", "qt_corrected", "qt_cubic")),
    # what is drawn
    Setting("weapons", "features", "bool", True, "armed zombies carry weapons (off: no socket read-back, no gather pass)"),
    Setting("readback_latency", "features", "int", 2, "frames between gathering a weapon socket and the CPU reading it",
            label="readback latency", low=1, high=3, slider=(1, 3)),
    Setting("shadows", "features", "bool", True, "sun shadows (the shadow map and pass exist only when on)"),
    Setting("culling", "features", "bool", True, "frustum culling"),
    Setting("occlusion", "features", "bool", False,
            "occlusion culling against the previous frame's depth pyramid (the gpu cull path; docs/BENCHMARKS.md says where it pays)"),
    Setting("lod_distances", "features", "ascending", (14.0, 40.0, 90.0), "metres from the camera where LOD1, LOD2 and LOD3 start",
            label="LOD distances", low=0, open_low=True, slider=(1, 500)),
    Setting("lod_error_px", "features", "float", 2.0,
            "pixels of the view drawn into (its height and field of view) that a generated LOD's measured error covers where it "
            "starts: a character whose file has no coarser LODs gets them made, each switched in where its error projects to this "
            "(the built-ins use lod_distances)", label="LOD error (px)", low=0, open_low=True, high=100, slider=(0.25, 8)),
    Setting("lod_fade", "features", "float", 2.0,
            "metres past each LOD switch (the impostors' too) over which the two LODs cross-fade, dithered, so no switch pops "
            "(0: they switch at once)", label="LOD fade", low=0, high=100, slider=(0, 10)),
    Setting("impostors", "features", "choice", "auto",
            "agents past impostor_distance drawn as animated impostors, one quad each, from an atlas baked at start and cached "
            "(crowd/draw/impostors.py); auto: where the crowd is large enough to need them (docs/BENCHMARKS.md says where)",
            choices=("auto", "on", "off")),
    Setting("impostor_distance", "features", "float", 60.0, "metres from the camera past which agents are drawn as impostors",
            label="impostor distance", low=0, open_low=True, slider=(5, 500)),
    Setting("town", "features", "bool", True,
            "streets to fight in: a built-in town of blocks, buildings, parked cars and barriers, repeating over the world; "
            "the crowd steers around it (off: the empty plane the benchmarks measure on)"),
    Setting("morphs", "features", "bool", True,
            "morph targets: each zombie's face and body shapes (its clips' snarl, its variation) drawn (off: no morph bake, "
            "no morph texture, the draw without morph code)"),
    Setting("survivor", "features", "bool", True,
            "the player is a survivor to play: a built-in character drawn in the crowd's passes, animated from its speed and "
            "actions, hurt by the zombies that reach it (off: the player is a point the zombies chase)"),
    Setting("foot_lock", "features", "bool", True,
            "feet that carry weight stay where they came down: the processor holds each planted foot through turns, pushes and "
            "blends, and solves the leg to it (two-bone IK; the compute path only; docs/ACCURACY.md)"),
    Setting("processor", "features", "choice", "auto", "animation processor path: compute where GL 4.3 exists, else fragment",
            label="processor path", choices=("auto", "compute", "fragment")),
    Setting("ai_path", "features", "choice", "auto",
            "where the crowd AI runs: gpu (compute passes, GL 4.3: every agent's state stays on the GPU and nothing per agent "
            "crosses to the CPU in a frame), cpu (the numpy AI, the GPU's float64 reference), auto: gpu where it can run "
            "(compute and the gpu cull path), else cpu", label="AI path", choices=("auto", "gpu", "cpu")),
    Setting("gl", "features", "choice", "auto",
            "the GL features the frame may use: auto (all the context has) or 4.1 (what macOS offers: no compute shaders, "
            "storage buffers or image load/store, so the fragment processor, the transform-feedback cull, morph deltas in textures, no foot "
            "lock or occlusion culling), forced on a context that has more", label="GL feature level", choices=("auto", "4.1")),
    Setting("cull", "features", "choice", "auto",
            "where culling, LOD picking and the per-draw instance lists are made: gpu (a compute pass and indirect draws, "
            "GL 4.3), feedback (a transform-feedback pass per list and indirect draws, GL 4.0: macOS) or cpu (numpy); "
            "auto: gpu where GL 4.3 exists, else feedback where GL 4.0 does, else cpu", label="cull path",
            choices=("auto", "gpu", "feedback", "cpu")),
    # the crowd's behaviour (crowd.sim.config.AIConfig)
    _ai("substep", 1 / 60, "seconds, the longest simulation substep (a frame up to 5 percent longer takes one)", low=0, open_low=True),
    _ai("max_dt", 0.25, "seconds: a longer frame is simulated as this long (the game slows, it does not explode)", low=0, high=10, open_low=True),
    _ai("notice_radius", 14.0, "metres at which a zombie notices the player", low=0, open_low=True),
    _ai("forget_radius", 24.0, "metres at which a chasing zombie gives up (at least notice_radius)", low=0, open_low=True),
    _ai("alert_rate", 0.3, "m/s: how fast the notice and forget radii grow as a round goes on (up to think_radius), so more of "
        "the horde notices the player; 0: they stay", low=0, high=100),
    _ai("start_clear", 25.0, "metres around the player kept free of zombies where a crowd starts: a round begins with the horde at "
        "a distance (it keeps its density outside; 0, or a crowd with no survivor: zombies anywhere)", low=0, high=10_000),
    _ai("reaction_min", 0.2, "seconds, shortest delay between noticing the player and chasing", low=0),
    _ai("reaction_max", 1.2, "seconds, longest such delay (at least reaction_min)", low=0),
    _ai("attack_reach", 1.2, "metres from the player at which a zombie attacks", low=0, open_low=True),
    _ai("attack_cooldown", 0.6, "seconds between attacks", low=0),
    _ai("separation_radius", 0.75, "metres between two person-sized agents' centres that separation keeps (a wider character's grows with its footprint)",
        low=0, open_low=True),
    _ai("separation_stiffness", 15.0, "1/s: share of an overlap removed per second (clamped at 1 per substep)", low=0),
    _ai("max_accel", 6.0, "m/s^2, steering acceleration limit", low=0, open_low=True),
    _ai("turn_rate", 5.0, "rad/s, heading turn limit", low=0, open_low=True),
    _ai("plant_feet", True, "feet kept planted through turns and pushes: a turning zombie near the player or the camera pivots "
        "on the foot it stands on, and a push along its heading steps its legs (docs/ACCURACY.md)", kind="bool"),
    _ai("arrive_distance", 1.5, "metres over which a zombie slows down as it arrives", low=0, open_low=True),
    _ai("wander_radius", 6.0, "metres, how far a wandering zombie picks its next point", low=0, open_low=True),
    _ai("wander_speed", 0.6, "share of the zombie's walk speed while wandering", low=0),
    _ai("speed_min", 0.8, "smallest per-zombie speed factor", low=0, open_low=True),
    _ai("speed_max", 1.2, "largest per-zombie speed factor (at least speed_min)", low=0, open_low=True),
    _ai("runner_share", 0.3, "share of zombies that run instead of shambling", low=0, high=1),
    _ai("armed_share", 0.5, "share of zombies that carry a weapon", low=0, high=1),
    _ai("crossfade", 0.25, "seconds of cross-fade in and out of every action", low=0, slider=(0.0, 1.5)),
    _ai("corpse_time", 6.0, "seconds a body lies still before the zombie respawns", low=0),
    _ai("health", 3, "hits that kill a zombie", kind="int", low=1, high=1000),
    _ai("area_per_agent", 6.0, "m^2 of world per zombie (sets the world size when half_extent is 0)", low=0, open_low=True),
    _ai("min_half_extent", 12.0, "metres, the smallest half width of the world", low=0, open_low=True),
    _ai("half_extent", 0.0, "metres, the world's half width; 0: from the zombie count", low=0),
    _ai("think_every", 8, "substeps between two thinks of a far zombie that wanders or lies dead (1: all think every substep)",
        kind="int", low=1, high=64),
    _ai("think_radius", 30.0, "metres from the player or the camera within which every zombie thinks every substep (at least notice_radius)", low=0),
    _ai("think_from", 20_000, "zombies from which the think budget is used (below, its fixed cost is more than it saves)", kind="int", low=0),
    _ai("workers", 0, "processes that step the crowd, this one included (0: one per core; 1: this process only); "
        "any number gives the same crowd", kind="int", low=0, high=64),
    # live controls of a running crowd (the panel; not in scene files)
    Setting("time_scale", "session", "float", 1.0, "simulated seconds per real second", label="time scale", low=0, high=10, slider=(0, 4)),
    Setting("clip_speed", "session", "float", 1.0, "a clip's playback speed; a faster walk also moves faster",
            label="playback speed", low=0.05, high=20, slider=(0.1, 3)),
    Setting("clip_loop", "session", "bool", True, "a clip loops (true) or plays once (false)", label="loop"),
    Setting("morph_weight", "session", "float", 0.0, "a morph target's weight: each end of a character's variation range (scene "
            "[[characters]] morph = { target = [lo, hi] })", label="morph weight", low=0, high=1, slider=(0, 1)),
    Setting("layer_weight", "session", "float", 1.0, "a layer's weight held at a value", label="weight", low=0, high=1000, slider=(0, 2)),
    # how long and how big (command line only)
    Setting("frames", "run", "int", 60, "frames to run (headless default 60; the window runs until closed)", low=1, high=100_000),
    Setting("size", "run", "size", (1280, 720), "frame size WxH", low=16, high=8192),
    Setting("view", "run", "choice", "auto",
            "the headless picture's camera: player (the horde around the player), horizon (high over the horde's near edge, "
            "across it to its far side: its scale), overview (every agent framed, the benchmarks' view); auto: horizon from "
            "10,000 agents, else player. A scene's [camera] comes first; the window's V key toggles the horizon view",
            choices=("auto", "player", "horizon", "overview")),
)

SETTINGS: dict[str, Setting] = {s.name: s for s in _ALL}
DEFAULTS: dict[str, object] = {s.name: s.default for s in _ALL}


def group(name: str) -> dict[str, Setting]:
    """The settings of one group, in declaration order."""
    return {s.name: s for s in _ALL if s.group == name}


SCENE_GROUPS = ("scene", "clips", "features", "ai")  # the groups a scene file holds, one TOML table each


def parse(name: str, text: str, error: type[Exception] = SettingError, source: str | None = None):
    """A command-line string for setting `name`, converted and checked (``Setting.check``)."""
    setting = SETTINGS[name]
    # A size is named as typed ("8x8", not [8, 8]); numbers as TOML would show them, so that a flag
    # and a scene file give the same line.
    return setting.check(setting.from_text(text), error, source, shown=text if setting.kind == "size" else None)
