"""The pipeline's run-time setting changes, the panel's and the command line's alike, through one
mechanism: ``LiveSettings.set(name, value)`` checks the value against crowd.settings, and the setting's
entry in ``LIVE`` says what it touches. A setting either tunes a running stage in place, or builds again
the stages whose builders read it (crowd.stages: every new one built before any old one goes, so a
failed build keeps the running ones and the old config), or runs the rest of its change (a new crowd,
atlases, a re-bake). Nothing else is rebuilt, and the crowd keeps its state.

``LiveSettings`` is a base of ``crowd.pipeline.CrowdPipeline``, which holds everything these change (the
config, the cast, the stages, the AI, the palette sync); it is not built on its own.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .anim.bake import AnimationBake
from .anim.foot_lock import bake_legs
from .cameras import overview_distance
from .cast import bake_member, character_motion, make_atlases, player_motion
from .gl import GL_LIMITS
from .pipeline_config import PipelineConfig, PipelineError
from .settings import SETTINGS, group
from .sim.ai import CrowdAI
from .sim.config import LAYERS, AIConfig
from .stages import CastPart, StageSpec, build_processor, build_readback, build_renderer, build_town, build_weapons

# Triangles the crowd's agents would draw at their coarsest LODs from which "auto" draws the far ones as
# impostors: 5,000 of the built-ins (138 each), where impostors were measured to pay (docs/BENCHMARKS.md,
# "Splatting the smallest impostors"); a character with heavier far LODs gets them with fewer agents.
IMPOSTOR_TRIANGLES = 5_000 * 138

AI_SETTINGS = group("ai")
BAKE_SETTINGS = ("bake_fps", "precision", "interpolation", "compression_bound_mm")
BUILT_WITH = ("model_scale", "survivor", "town", "gl", "ai_path")  # what the cast, its world and its GL paths are


def far_triangles(character, switches: int) -> float:
    """Triangles one agent of `character` draws at its coarsest drawn LOD (the one past the last of its
    `switches` switch distances; those past it cast shadows only), a variation group's choices averaged."""
    lod = min(max((m.lod for m in character.meshes), default=0), switches)
    at = [m for m in character.meshes if m.lod == lod]
    groups = {m.group for m in at if m.group}
    return sum(m.triangle_count for m in at if not m.group) + sum(
        float(np.mean([m.triangle_count for m in at if m.group == g])) for g in groups)


@dataclass(frozen=True)
class Live:
    """How a running crowd takes one setting, in this order: `rebuild` names the stages built again from
    the changed config; `tune` changes a running stage in place; `then` runs the rest of the change with
    the new config in place (it is put back if `then` fails). `field`: the PipelineConfig field it sets
    (None: `then` sets what it changes); a value equal to the field's runs nothing."""

    field: str | None
    rebuild: tuple[str, ...] = ()
    tune: Callable | None = None
    then: Callable | None = None
    repeat: bool = False  # run even when the value is the one set (a new crowd from the same seed)


# The stage builders, by the name crowd.stages.Stages keeps them under; each reads the StageSpec fields
# its stage is built from, and a setting that changes one of them rebuilds that stage.
BUILDERS = {
    "processor": lambda p, parts, spec: build_processor(p.ctx, parts, spec, p.counts),
    "renderer": lambda p, parts, spec: build_renderer(p.ctx, parts, spec),
    "weapons": lambda p, parts, spec: build_weapons(p.ctx, parts, spec),
    "town": lambda p, parts, spec: build_town(p.ctx, spec),
    "readback": lambda p, parts, spec: build_readback(p.ctx, p.processor, spec),
}


class LiveSettings:
    """The setting changes of a running crowd pipeline (a base of crowd.pipeline.CrowdPipeline)."""

    def set(self, name: str, value) -> None:
        """Set one setting of crowd.settings by name on the running crowd, through its entry in LIVE;
        PipelineError (one line) for a value it cannot take, a setting applied only when the crowd is
        built, or a name that is not a live setting. A refused change leaves the crowd as it was."""
        if name in BUILT_WITH:
            SETTINGS[name].check(value, PipelineError)
            raise PipelineError(f"{SETTINGS[name].words} is applied when the crowd is built: save the scene and run it again")
        live = LIVE.get(name)
        if live is None:
            raise PipelineError(f"{name!r} is not a setting a running crowd takes")
        value = SETTINGS[name].check(value, PipelineError)
        before = self.config
        if live.field is not None and getattr(before, live.field) == value and not live.repeat:
            return
        config = before if live.field is None else dataclasses.replace(before, **{live.field: value})
        if live.rebuild:
            self._replace_stages(live.rebuild, self._spec(config=config))
        if live.tune is not None:
            live.tune(self, value)
        self.config = config
        if live.then is not None:
            try:
                live.then(self, value)
            except BaseException:
                self.config = before
                raise

    def _replace_stages(self, names, spec: StageSpec, parts: list[CastPart] | None = None) -> None:
        """The stages `names` built again for `spec` (and `parts`, the cast's by default), all of them
        before any old one goes, so a build that fails keeps the running stages; a new processor drops
        the palettes and read-backs kept against the old one."""
        parts = self._parts() if parts is None else parts
        built: dict = {}
        try:
            for name in names:
                built[name] = BUILDERS[name](self, parts, spec)
        except BaseException:
            for stage in built.values():
                if stage is not None:
                    stage.release()
            raise
        for name, stage in built.items():
            self.stages.replace(name, stage)
        if "processor" in built:
            self._forget_history()

    # -- the stages' spec

    def _armed(self, config: PipelineConfig) -> bool:
        """Whether a crowd built from `config` needs the weapon stages. Only building and switching weapons
        ask this; once built, the stages that exist say it (an armed share set to 0 at run time keeps
        them, with nobody to gather)."""
        return config.weapons and config.ai.armed_share > 0 and any(m.character.armed for m in self.cast)

    def _spec(self, armed: bool | None = None, config: PipelineConfig | None = None) -> StageSpec:
        """The StageSpec of `config` (this pipeline's by default); `armed` defaults to whether the
        read-back stage exists."""
        c = self.config if config is None else config
        return StageSpec(layers=LAYERS, processor_path=c.processor_path, interpolation=c.interpolation, lod_distances=c.lod_distances,
                         shadows=c.shadows, culling=c.culling, occlusion=c.occlusion, armed=self.readback is not None if armed is None else armed,
                         readback_latency=c.readback_latency, cull=c.cull, foot_lock=c.foot_lock, town=c.town,
                         impostor_distance=c.impostor_distance, lod_fade=c.lod_fade, lod_error_px=c.lod_error_px, gl_limit=GL_LIMITS[c.gl])

    @property
    def latency(self) -> int:
        """Frames between gathering a weapon socket and the CPU reading it (the readback_latency setting)."""
        return self.config.readback_latency

    # -- impostors (crowd.draw.impostors): only where the scene needs them

    def impostors_needed(self) -> bool:
        """Whether the crowd's far agents are drawn as impostors: setting "on", or "auto" where its agents
        would draw at least IMPOSTOR_TRIANGLES at their coarsest LODs (fewer fit as meshes), spread wide
        enough that the camera framing them all has some past the impostor distance."""
        mode = SETTINGS["impostors"].check(self.config.impostors, PipelineError)
        if mode != "auto":
            return mode == "on"
        members = self.cast[:self.crowd_cast]
        load = sum(count * far_triangles(m.character, len(m.character.lod_distances or self.config.lod_distances))
                   for m, count in zip(members, self.counts))
        if load < IMPOSTOR_TRIANGLES:
            return False
        half = self.ai.half_extent
        reach = overview_distance(half) + half * math.sqrt(2.0)  # the overview camera's distance, then the farthest corner
        return reach >= self.config.impostor_distance

    def _make_impostors(self, bakes=None) -> bool:
        """Each crowd character's atlas made for its bake (or `bakes`, one per character of the cast, about
        to be used), from the cache where it holds one, or dropped, as the scene needs; True where that
        changed anything (the processor and renderer must then be built again)."""
        changed, notes = make_atlases(self.ctx, self.cast[:self.crowd_cast], bakes or [m.bake for m in self.cast],
                                      self.impostors_needed(), GL_LIMITS[self.config.gl])
        self.impostor_notes.extend(notes)
        return changed

    def _refresh_impostors(self, _value=None) -> None:
        """After a change that may change what needs impostors: atlases made or dropped, and the processor
        (which writes the keys) and the renderer (which draws them) built again where they did."""
        if self._make_impostors():
            self._replace_stages(("processor", "renderer"), self._spec())

    def _forget_history(self) -> None:
        """After a new processor: the foot lock's steps, the palettes kept and the read-backs queued against
        the old one are gone."""
        self.lock_steps.reset()
        self.sync.reset()
        if self.readback is not None:
            self.readback.reset()

    def _set_palette_history(self, history: int) -> None:
        """A new palette ring: the frames kept and the read-backs queued against the old one are gone."""
        self.processor.set_history(history)
        self.sync.reset(self.processor.history)
        if self.readback is not None:
            self.readback.reset()

    # -- what the settings whose change is more than a stage run (LIVE's `then`)

    def _switch_weapons(self, _on: bool) -> None:
        """Weapons on: the read-back stage, weapon meshes and a palette ring appear; off: all of them go."""
        spec = self._spec(self._armed(self.config))
        if spec.armed == (self.readback is not None):
            return
        self._replace_stages(("readback", "weapons"), spec)
        for cull in (self.renderer.gpu, self.renderer.feedback):
            if cull is not None:
                cull.set_visibility(spec.armed)  # the weapons' GPU cull reads it
        if not spec.armed:
            self.last.read = None
        self._set_palette_history(spec.history)

    def _new_latency(self, _frames: int) -> None:
        """1 to 3 frames. The palette ring is reallocated, so weapons are hidden for that many frames."""
        if self.readback is not None:
            self._set_palette_history(self._spec().history)

    def _set_ai(self, name: str, value) -> None:
        # (A crowd on the GPU reads the settings as uniforms, each step: nothing of it to read back.)
        self.set_ai_config(dataclasses.replace(self.config.ai, **{name: value}))

    def set_ai_config(self, config: AIConfig) -> None:
        """Every AI setting at once (a scene's, a benchmark's)."""
        self.ai.set_config(self._crowd_ai_config(config, self.survivor is not None))
        self.config = dataclasses.replace(self.config, ai=self.ai.config)

    def _crowd_ai_config(self, config: AIConfig, survivor: bool) -> AIConfig:
        """The AI settings a crowd runs with: the clear start is a round's, so a crowd with no survivor to
        play starts anywhere."""
        return config if survivor else dataclasses.replace(config, start_clear=0.0)

    def _bake_setting(self, name: str, value) -> None:
        """A bake setting: the cast baked again with it (the others as they are), or processed with it."""
        bake = self.bake
        now = {"bake_fps": bake.fps, "precision": bake.precision, "interpolation": self.processor.interpolation,
               "compression_bound_mm": bake.bound_mm, name: value}
        self.rebake(now["bake_fps"], now["precision"], now["interpolation"], now["compression_bound_mm"])

    def _morphs(self, on: bool) -> None:
        """Morph targets drawn (the cast baked again with its weight tracks, the processor writing pairs,
        the draw reading them) or not (none of it exists)."""
        self.use_bake(tuple(bake_member(self.cast, k, self.config.seed, m.bake.fps, m.bake.precision, m.bake.bound_mm, on)
                            for k, m in enumerate(self.cast)))

    def _resize(self, agents: int) -> None:
        """The crowd at `agents` agents: each character keeps its first agents, the new ones spawn."""
        before = self.ai.n
        self.ai.resize(agents)
        if self.gpu_crowd is not None:  # the kept agents copied on the GPU, the new ones spawned there
            self.gpu_crowd.gpu.resize_from(self.ai)
        self._crowd_since = self.frames
        moves = list(self.ai.moved)  # each character keeps its first agents, at its block's new place
        if self.survivor is not None:
            moves.append((before, agents, 1))  # the survivor's row follows the crowd's
        self.foot_skate.reset()  # (the sample is spread over the new count)
        self.processor.resize(self.counts)
        self.layers = np.empty((agents, LAYERS, 4), np.float32)
        self.sync.resize(self.rows, self.frames, moves)
        self.lock_steps.reset()  # made anew from where everyone stands; a kept agent steps 0 once
        if any(b != a for b, a, _ in moves[1:]) and self.readback is not None:
            self.readback.reset()  # the sockets queued were gathered for agents that have moved
        self._refresh_impostors()

    def _new_crowd(self, seed: int) -> None:
        """Every agent anew from `seed` (same count, settings and clips)."""
        old, self.ai = self.ai, CrowdAI(self.agents, seed, [m.motion for m in self.cast[:self.crowd_cast]], self.ai.config,
                                        self.config.origin, shares=self.ai.shares, obstacles=self.obstacles)
        self.ai.take_workers(old)
        if self.survivor is not None:
            self.ai.player = self.survivor.position.copy()
        self._blows_seen = 0
        old.close()
        if self.gpu_crowd is not None:
            self.gpu_crowd.load(self.ai, fresh=True)
        self._crowd_since = self.frames
        self.foot_skate.reset()
        self.processor.reset_lock()  # other agents now: nothing held is theirs
        self.lock_steps.reset()
        self.sync.spawned(slice(None), self.frames)

    @contextlib.contextmanager
    def _numpy_ai(self):
        """A change made through the numpy AI to a crowd that lives on the GPU: it is read back first and
        handed to the GPU again after (an event, not a frame: a resize, new settings, new clips)."""
        crowd = getattr(self, "gpu_crowd", None)
        if crowd is not None:
            crowd.store()
        yield
        if crowd is not None:
            crowd.load(self.ai)

    # -- re-bakes and clips: events with more than one value

    def rebake(self, fps: float | str, precision: str, interpolation: str | None = None, bound_mm: float | None = None) -> None:
        """Bake the scene's clips again at another rate, precision or compression bound, or process them
        with another interpolation, live: a new bake and processor replace the old ones (released), and
        the crowd keeps its state."""
        self.use_bake(self.make_bake(fps, precision, bound_mm), interpolation)

    def make_bake(self, fps: float | str, precision: str, bound_mm: float | None = None, report=None) -> tuple[AnimationBake, ...]:
        """New bakes of the scene's clips, one per character of the cast (CPU only, no GL: a thread may
        run it while frames go on); `report` is crowd.progress's callback."""
        bound_mm = self.config.compression_bound_mm if bound_mm is None else bound_mm
        return tuple(bake_member(self.cast, k, self.config.seed, fps, precision, bound_mm, self.config.morphs, report)
                     for k in range(len(self.cast)))

    def use_bake(self, bakes, interpolation: str | None = None) -> None:
        """Process `bakes` (from make_bake: one per character) from now on, with `interpolation` (None: the
        current one): a new processor replaces the old one (released), and the crowd keeps its state."""
        bakes = (bakes,) if isinstance(bakes, AnimationBake) else tuple(bakes)
        if len(bakes) != len(self.cast):
            raise PipelineError(f"{len(bakes)} bakes for a cast of {len(self.cast)} characters")
        interpolation = self.config.interpolation if interpolation is None else interpolation
        for member, bake in zip(self.cast, bakes):
            for i, clip in enumerate(bake.clips):  # loop settings made in the panel survive the re-bake
                old = next((c for c in member.bake.clips if c.name == clip.name), None)
                if old is not None:
                    bake.clips[i] = dataclasses.replace(clip, loop=old.loop)
        impostors_changed = self._make_impostors(bakes)  # an atlas shows its bake's clips: a new bake, a new atlas
        parts = [CastPart(m.character, bake, m.masks, bake_legs(m.character.skeleton, bake), m.impostor) for m, bake in zip(self.cast, bakes)]
        # The draw reads the morph pairs and impostor keys the processor writes: it follows where they change.
        morphs_changed = tuple(b.morphs is not None for b in bakes) != self.renderer.morphs
        stages = ("processor", "renderer") if morphs_changed or impostors_changed else ("processor",)
        self._replace_stages(stages, dataclasses.replace(self._spec(), interpolation=interpolation), parts)
        for member, part in zip(self.cast, parts):
            member.bake, member.legs = part.bake, part.legs
        bake = bakes[0]
        self.config = dataclasses.replace(self.config, bake_fps=bake.fps, precision=bake.precision, interpolation=interpolation,
                                          compression_bound_mm=bake.bound_mm)
        with self._numpy_ai():
            for k, member in enumerate(self.cast[:self.crowd_cast]):
                member.motion = character_motion(self.cast, k)
                self.ai.set_motion(member.motion, k)
        if self.survivor is not None:
            self.survivor.motion = player_motion(self.cast[-1])

    def set_clip_speed(self, name: str, speed: float, character: int = 0) -> None:
        """A clip's playback speed (three.js's timeScale), of one character of the cast. Locomotion clips
        move the zombie faster too, so their feet stay planted; actions end sooner."""
        member = self.member(character)
        member.bake.clip_index(name)
        speeds = {**member.clip_speed, name: float(speed)}
        if int(character) >= self.crowd_cast:  # the survivor's clips: its controller's durations
            SETTINGS["clip_speed"].check(float(speed), PipelineError, f"clip {name!r}")
            member.clip_speed = {k: v for k, v in speeds.items() if v != 1.0}
            self.survivor.motion = player_motion(self.cast[-1])
            return
        motion = character_motion(self.cast, int(character), speeds)  # checks the range
        member.clip_speed = {k: v for k, v in speeds.items() if v != 1.0}
        member.motion = motion
        with self._numpy_ai():
            self.ai.set_motion(motion, int(character))

    def set_clip_loop(self, name: str, loop: bool, character: int = 0) -> None:
        member = self.member(character)
        self.processor.set_clip_loop(member.bake.clip_index(name), loop, int(character))


def _tune(setter: str):
    """A LIVE `tune` that hands the value to one of the renderer's live setters."""
    return lambda p, value: getattr(p.renderer, setter)(value)


def _renderer_attribute(name: str):
    """A LIVE `tune` that sets one of the renderer's live attributes."""
    return lambda p, value: setattr(p.renderer, name, value)


# Every setting a running crowd takes, and what it touches. The ones a scene sets when the crowd is built
# are BUILT_WITH; "time_scale" is the session's own.
LIVE = {
    "agents": Live("agents", then=LiveSettings._resize),
    "seed": Live("seed", then=LiveSettings._new_crowd, repeat=True),
    **{name: Live(None, then=lambda p, value, name=name: p._bake_setting(name, value)) for name in BAKE_SETTINGS},
    **{name: Live(None, then=lambda p, value, name=name: p._set_ai(name, value)) for name in AI_SETTINGS},
    "morphs": Live("morphs", then=LiveSettings._morphs),
    "processor": Live("processor_path", rebuild=("processor",)),
    "foot_lock": Live("foot_lock", rebuild=("processor",)),
    "shadows": Live("shadows", rebuild=("renderer", "weapons", "town")),  # the shaders and the shadow map
    "cull": Live("cull", rebuild=("renderer", "weapons", "town")),  # each culled where the bodies are
    "culling": Live("culling", tune=_renderer_attribute("culling")),
    "occlusion": Live("occlusion", tune=_tune("set_occlusion")),
    "lod_distances": Live("lod_distances", tune=_renderer_attribute("lod_distances")),
    "lod_fade": Live("lod_fade", tune=_tune("set_lod_fade")),
    "lod_error_px": Live("lod_error_px", tune=_tune("set_lod_error_px")),
    "impostor_distance": Live("impostor_distance", tune=_tune("set_impostor_distance"), then=LiveSettings._refresh_impostors),
    "impostors": Live("impostors", then=LiveSettings._refresh_impostors),
    "weapons": Live("weapons", then=LiveSettings._switch_weapons),
    "readback_latency": Live("readback_latency", then=LiveSettings._new_latency),
}
