"""The pipeline's run-time setting changes, the panel's and the command line's alike: each checks its
value, rebuilds only the stage it touches (through crowd.stages, each new stage built before the old one
goes, so a failed build keeps the running one) and keeps the crowd's state. A re-bake, the impostors a
crowd needs, a new crowd from another seed or count are here too.

``LiveSettings`` is a base of ``crowd.pipeline.CrowdPipeline``, which holds everything these change (the
config, the cast, the stages, the AI, the palette sync); it is not built on its own.
"""

from __future__ import annotations

import contextlib

import dataclasses
import math

import numpy as np

from .anim.bake import AnimationBake
from .anim.foot_lock import bake_legs
from .cameras import overview_distance
from .cast import bake_member, character_motion, make_atlases, player_motion
from .gl import GL_LIMITS
from .pipeline_config import PipelineConfig, PipelineError
from .settings import SETTINGS
from .sim.ai import CrowdAI
from .sim.config import LAYERS, AIConfig
from .stages import CastPart, StageSpec, build_processor, build_readback, build_renderer, build_weapons
from .stages import build_town as build_town_stage

# Triangles the crowd's agents would draw at their coarsest LODs from which "auto" draws the far ones as
# impostors: 5,000 of the built-ins (138 each), where impostors were measured to pay (docs/BENCHMARKS.md,
# "Splatting the smallest impostors"); a character with heavier far LODs gets them with fewer agents.
IMPOSTOR_TRIANGLES = 5_000 * 138


def far_triangles(character, switches: int) -> float:
    """Triangles one agent of `character` draws at its coarsest drawn LOD (the one past the last of its
    `switches` switch distances; those past it cast shadows only), a variation group's choices averaged."""
    lod = min(max((m.lod for m in character.meshes), default=0), switches)
    at = [m for m in character.meshes if m.lod == lod]
    groups = {m.group for m in at if m.group}
    return sum(m.triangle_count for m in at if not m.group) + sum(
        float(np.mean([m.triangle_count for m in at if m.group == g])) for g in groups)


class LiveSettings:
    """The setting changes of a running crowd pipeline (a base of crowd.pipeline.CrowdPipeline)."""

    # -- the stages' spec

    def _armed(self, config: PipelineConfig) -> bool:
        """Whether a crowd built from `config` needs the weapon stages. Only building and switching weapons
        ask this; once built, the stages that exist say it (an armed share set to 0 at run time keeps
        them, with nobody to gather)."""
        return config.weapons and config.ai.armed_share > 0 and any(m.character.armed for m in self.cast)

    def _spec(self, armed: bool | None = None) -> StageSpec:
        """The StageSpec of this pipeline now; `armed` defaults to whether the read-back stage exists."""
        c = self.config
        return StageSpec(layers=LAYERS, processor_path=c.processor_path, interpolation=c.interpolation, lod_distances=c.lod_distances,
                         shadows=c.shadows, culling=c.culling, occlusion=c.occlusion, armed=self.readback is not None if armed is None else armed,
                         readback_latency=self.latency, cull=c.cull, foot_lock=c.foot_lock, town=c.town,
                         impostor_distance=c.impostor_distance, lod_fade=c.lod_fade, lod_error_px=c.lod_error_px, gl_limit=GL_LIMITS[c.gl])

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

    def _refresh_impostors(self) -> None:
        """After a change that may change what needs impostors: atlases made or dropped, and the processor
        (which writes the keys) and the renderer (which draws them) built again where they did."""
        if self._make_impostors():
            self._rebuild(self._parts(), self._spec(), renderer=True)

    def _rebuild(self, parts: list[CastPart], spec: StageSpec, renderer: bool) -> None:
        """A new processor for `parts` (and a new renderer, with `renderer`), each built before the old one
        goes, so a build that fails keeps the running stages; the palettes and read-backs kept against the
        old processor are dropped."""
        processor = build_processor(self.ctx, parts, spec, self.counts)
        new_renderer = None
        if renderer:
            try:
                new_renderer = build_renderer(self.ctx, parts, spec)
            except BaseException:
                processor.release()
                raise
        self.stages.replace("processor", processor)
        if new_renderer is not None:
            self.stages.replace("renderer", new_renderer)
        self._forget_history()

    def _forget_history(self) -> None:
        """After a new processor: the foot lock's steps, the palettes kept and the read-backs queued against
        the old one are gone."""
        self.lock_steps.reset()
        self.sync.reset()
        if self.readback is not None:
            self.readback.reset()

    def set_lod_fade(self, metres: float) -> None:
        """Cross-fade each LOD switch over `metres` (0: switch at once), live."""
        metres = SETTINGS["lod_fade"].check(metres, PipelineError)
        self.renderer.set_lod_fade(metres)
        self.config = dataclasses.replace(self.config, lod_fade=metres)

    def set_lod_error_px(self, pixels: float) -> None:
        """Generated LODs switch where their error covers `pixels`, live."""
        pixels = SETTINGS["lod_error_px"].check(pixels, PipelineError)
        self.renderer.set_lod_error_px(pixels)
        self.config = dataclasses.replace(self.config, lod_error_px=pixels)

    def set_impostors(self, mode: str) -> None:
        """Impostors "auto", "on" or "off", live."""
        mode = SETTINGS["impostors"].check(mode, PipelineError)
        self.config = dataclasses.replace(self.config, impostors=mode)
        self._refresh_impostors()

    def set_impostor_distance(self, metres: float) -> None:
        metres = SETTINGS["impostor_distance"].check(metres, PipelineError)
        self.config = dataclasses.replace(self.config, impostor_distance=metres)
        self.renderer.set_impostor_distance(metres)
        self._refresh_impostors()

    # -- run-time settings: the panel and the command line both come through these

    def _set_palette_history(self, history: int) -> None:
        """A new palette ring: the frames kept and the read-backs queued against the old one are gone."""
        self.processor.set_history(history)
        self.sync.reset(self.processor.history)
        if self.readback is not None:
            self.readback.reset()

    def set_shadows(self, on: bool) -> None:
        """Shadows decide the shaders and the shadow map, so switching them builds the renderer (and
        the weapons' programs) again; the old objects are released."""
        if bool(on) == self.renderer.shadows:
            return
        self.config = dataclasses.replace(self.config, shadows=bool(on))
        spec = self._spec()
        self.stages.replace("renderer", build_renderer(self.ctx, self._parts(), spec))
        if self.weapons is not None:
            self.stages.replace("weapons", build_weapons(self.ctx, self._parts(), spec))
        if self.town is not None:
            self.stages.replace("town", build_town_stage(self.ctx, spec))

    def set_cull_path(self, path: str) -> None:
        """Cull on the GPU or the CPU from the next frame: the renderer is built again for it."""
        path = SETTINGS["cull"].check(path, PipelineError)
        spec = dataclasses.replace(self._spec(), cull=path)
        renderer = build_renderer(self.ctx, self._parts(), spec)
        try:
            weapons = build_weapons(self.ctx, self._parts(), spec)  # culled where the bodies are
        except BaseException:
            renderer.release()
            raise
        self.stages.replace("renderer", renderer)
        self.stages.replace("weapons", weapons)
        self.config = dataclasses.replace(self.config, cull=path)

    def set_culling(self, on: bool) -> None:
        self.config = dataclasses.replace(self.config, culling=bool(on))
        self.renderer.culling = bool(on)

    def set_occlusion(self, on: bool) -> None:
        """Occlusion culling on (the depth pyramid appears, on the gpu cull path) or off (it goes)."""
        self.config = dataclasses.replace(self.config, occlusion=bool(on))
        self.renderer.set_occlusion(bool(on))

    def set_lod_distances(self, *distances: float) -> None:
        distances = SETTINGS["lod_distances"].check(distances, PipelineError)
        self.config = dataclasses.replace(self.config, lod_distances=distances)
        self.renderer.lod_distances = distances

    def set_weapons(self, on: bool) -> None:
        """Weapons on: the read-back stage, weapon meshes and a palette ring appear; off: all of them go."""
        config = dataclasses.replace(self.config, weapons=bool(on))
        spec = self._spec(self._armed(config))
        if spec.armed != (self.readback is not None):
            # Both new stages exist before either old one goes, so a failed build keeps the running pair.
            readback = build_readback(self.ctx, self.processor, spec)
            try:
                weapons = build_weapons(self.ctx, self._parts(), spec)
            except BaseException:
                if readback is not None:
                    readback.release()
                raise
            self.stages.replace("readback", readback)
            self.stages.replace("weapons", weapons)
            for cull in (self.renderer.gpu, self.renderer.feedback):
                if cull is not None:
                    cull.set_visibility(spec.armed)  # the weapons' GPU cull reads it
            if not spec.armed:
                self.last.read = None
            self._set_palette_history(spec.history)
        self.config = config

    def _crowd_ai_config(self, config: AIConfig, survivor: bool) -> AIConfig:
        """The AI settings a crowd runs with: the clear start is a round's, so a crowd with no survivor to
        play starts anywhere."""
        return config if survivor else dataclasses.replace(config, start_clear=0.0)

    def set_ai_config(self, config: AIConfig) -> None:
        # (A crowd on the GPU reads the settings as uniforms, each step: nothing of it to read back.)
        self.ai.set_config(self._crowd_ai_config(config, self.survivor is not None))
        self.config = dataclasses.replace(self.config, ai=self.ai.config)

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
        self._rebuild(parts, dataclasses.replace(self._spec(), interpolation=interpolation), renderer=morphs_changed or impostors_changed)
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

    def set_morphs(self, on: bool) -> None:
        """Morph targets drawn (the cast baked again with its weight tracks, the processor writing pairs,
        the draw reading them) or not (none of it exists), live."""
        on = SETTINGS["morphs"].check(on, PipelineError)
        if on == self.config.morphs:
            return
        bakes = tuple(bake_member(self.cast, k, self.config.seed, m.bake.fps, m.bake.precision, m.bake.bound_mm, on)
                      for k, m in enumerate(self.cast))
        self.use_bake(bakes)
        self.config = dataclasses.replace(self.config, morphs=on)

    def set_processor_path(self, path: str) -> None:
        """Run the same bake on another processor path (compute, fragment or auto), live."""
        path = SETTINGS["processor"].check(path, PipelineError)
        processor = build_processor(self.ctx, self._parts(), dataclasses.replace(self._spec(), processor_path=path), self.counts)
        self.stages.replace("processor", processor)
        self.config = dataclasses.replace(self.config, processor_path=path)
        self._forget_history()

    def set_foot_lock(self, on: bool) -> None:
        """The foot lock on (a processor that holds planted feet, with its state buffers) or off (a
        processor without them, the lock's code compiled out), live; the crowd keeps its state."""
        on = SETTINGS["foot_lock"].check(on, PipelineError)
        processor = build_processor(self.ctx, self._parts(), dataclasses.replace(self._spec(), foot_lock=on), self.counts)
        self.stages.replace("processor", processor)
        self.config = dataclasses.replace(self.config, foot_lock=on)
        self._forget_history()

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

    def set_agent_count(self, agents: int) -> None:
        agents = SETTINGS["agents"].check(agents, PipelineError)
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
        self.config = dataclasses.replace(self.config, agents=agents)
        self._refresh_impostors()

    def set_seed(self, seed: int) -> None:
        """A new crowd from another seed (same count, settings and clips); every agent starts anew."""
        seed = SETTINGS["seed"].check(seed, PipelineError)
        self.config = dataclasses.replace(self.config, seed=seed)
        self._new_crowd(seed)

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

    def set_readback_latency(self, latency: int) -> None:
        """1 to 3 frames. The palette ring is reallocated, so weapons are hidden for `latency` frames."""
        self.latency = SETTINGS["readback_latency"].check(latency, PipelineError)
        if self.readback is not None:
            self._set_palette_history(self._spec().history)
