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

A crowd of several characters (``PipelineConfig.characters``: each a model, its share of the crowd and its
roles): each character is loaded, its roles matched and its clips baked on its own (``CastMember``), and
the AI keeps each one's agents in a block of its own, in the cast's order (crowd.frame). The stages take
the whole cast: the processor runs a dispatch per character into one palette, the renderer culls every
agent in one pass and draws each character's pieces from lists of their own, and the weapons are every
armed character's props, numbered across the cast. ``character``, ``bake``, ``roles`` and ``motion`` are
the first character's (the only one's in a crowd of one).
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import moderngl
import numpy as np

from .allocator import keep_freed_memory
from .anim.bake import AnimationBake, bake
from .anim.foot_lock import bake_legs
from .anim.foot_skate import FootSkateMonitor
from .anim.processor import AnimationProcessor, palette_joint_positions
from .anim.morph import NOT_HELD, MorphError, bake_morphs
from .anim.roles import clips_used, match_roles
from .asset.gltf import load_character
from .asset.model import Character, cast_weapons
from .draw.impostors import HELD_GROUP
from .draw.readback import RING, SocketRead, SocketReadback
from .draw.render import CrowdRenderer, FrameView, view_proj
from .draw.sync import PaletteSync
from .draw.weapons import AgentFrames, WeaponRenderer
from .frame import Camera, FrameError, Instances, LayerOverrides, cast_counts, cast_firsts
from .gl import GL_LIMITS, GLStage
from .lighting import LIGHTING
from .progress import bar
from .settings import DEFAULTS, SETTINGS
from .spans import over_spans
from .sim.ai import DYING, LAYERS, AIConfig, CrowdAI, Motion, PlayerScript, motion_for, upper_body_mask
from .sim.player import ROLES as SURVIVOR_ROLES
from .sim.player import STRIKE_REACH, Survivor, SurvivorMotion, survivor_motion
from .asset.town import build_town
from .draw.town import TownRenderer
from .stages import CastPart, StageSpec, Stages, build_processor, build_readback, build_renderer, build_weapons
from .stages import build_town as build_town_stage
from .timing import PassTimer, SampleRing

# The default camera's neighbourhood of the player in a crowd too big to frame whole, and how far it sees
# then: where the fog (crowd.lighting) has hidden 95 % of what is there, so the crowd fades out rather
# than stopping at the far plane.
VIEW_RADIUS_M = 20.0
FOG_FAR_M = -math.log(0.05) / LIGHTING["u_fog_density"]
FOOT_SKATE_SAMPLE = 32  # agents whose feet are read back for the stats' foot_skate: 128 entries beside the sockets
TOWN_CIRCLE_M = 9.0  # the headless player's circle in a town: round the crossing, clear of the buildings at its corners


# Agents from which "auto" draws the far ones as impostors: fewer fit the frame as meshes (docs/BENCHMARKS.md,
# "Impostors").
IMPOSTOR_AGENTS = 20_000

class PipelineError(ValueError):
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


@dataclass(eq=False)
class CastMember:
    """One character of the running crowd: its spec, what was loaded and baked for it, and its clips'
    playback speeds. A member is an identity, not a value: a cast may hold one model twice, and its
    members compare (and hash) as themselves, never field by field."""

    spec: CharacterSpec
    character: Character
    roles: dict
    role_notes: list
    bake: AnimationBake
    legs: object  # crowd.anim.foot_lock.Legs (possibly empty)
    masks: np.ndarray | None
    motion: Motion | None = None
    clip_speed: dict = field(default_factory=dict)  # clip name → playback speed (time scale), where not 1
    player: bool = False  # the survivor the player plays, not one of the crowd
    impostor: object = None  # its ImpostorAtlas (crowd.draw.impostors) where the scene draws its far agents as impostors

    def part(self) -> CastPart:
        return CastPart(self.character, self.bake, self.masks, self.legs, self.impostor)

    @property
    def name(self) -> str:
        return self.character.name


@dataclass
class FrameState:
    """What the last frame decided, kept until the next one replaces it whole."""

    index: int = -1  # the frame number (-1: none yet)
    view: FrameView | None = None  # the camera, view and light matrices and visible set every pass got
    read: SocketRead | None = None  # the socket read-back that arrived in this frame (from frame index - N)
    row_offset: int | np.ndarray = 0  # the first palette row each agent was drawn from
    agent_frames: AgentFrames | None = None  # where each agent stood, for the weapons


class CrowdPipeline(GLStage):
    def __init__(self, ctx: moderngl.Context, config: PipelineConfig):
        keep_freed_memory()  # the frame's numpy temporaries reuse memory instead of faulting it in anew (crowd.allocator)
        self.stages = Stages()  # nothing yet: a failure before the build below releases nothing
        self.ai: CrowdAI | None = None  # likewise: its worker processes start with a big enough crowd's first step
        self.timer = PassTimer(ctx)
        SETTINGS["agents"].check(config.agents, PipelineError)
        SETTINGS["gl"].check(config.gl, PipelineError)
        self.ctx = ctx
        self.config = config
        with bar(4, "starting the crowd: the character", "step") as started:  # on a terminal only (crowd.progress)
            self._build(ctx, config, started)

    def _build(self, ctx: moderngl.Context, config: PipelineConfig, started) -> None:
        """The characters, their bakes, the crowd and the GPU stages, each step shown on `started`'s bar."""
        specs = config.cast()
        try:
            cast_counts(0, [s.share for s in specs])
        except FrameError as exc:
            raise PipelineError(str(exc)) from None
        self.cast: list[CastMember] = []
        for spec in specs:
            character = load_character(spec.model, scale=SETTINGS["model_scale"].check(spec.model_scale, PipelineError))
            roles, notes = match_roles(character.clips, spec.roles)
            if len(specs) > 1:
                notes = [f"{character.name}: {note}" for note in notes]
            masks = upper_body_mask(character.skeleton)
            self.cast.append(CastMember(spec, character, roles, notes, None, None, masks))
        if config.survivor:  # the player's character: the cast's last, one agent after the crowd's
            character = load_character("survivor")
            self.cast.append(CastMember(CharacterSpec("survivor", 0.0), character, {r: r for r in SURVIVOR_ROLES}, [], None, None,
                                        upper_body_mask(character.skeleton), player=True))
        started.update(1)
        started.set_description("starting the crowd: the bake")
        # Leave out what the scene does not need: only the clips the roles play are baked.
        for k, member in enumerate(self.cast):
            member.bake = self._bake(k, config.bake_fps, config.precision, config.compression_bound_mm)
            member.legs = bake_legs(member.character.skeleton, member.bake)  # what the foot lock holds, if it runs
        started.update(1)
        started.set_description(f"starting the crowd: {config.agents:,} agents")
        self._lock_ground: np.ndarray | None = None  # each agent's ground point (2, N: x, z) at the last run, float64
        self._lock_motion_rows = np.empty((0, 4), np.float32)
        self.latency = SETTINGS["readback_latency"].check(config.readback_latency, PipelineError)
        self.crowd_cast = len(specs)  # the cast's first characters are the crowd's; a survivor comes after them
        for k in range(self.crowd_cast):
            self.cast[k].motion = self._motion(k)
        # The town's obstacles, which the crowd steers around (the town's meshes are the town stage's).
        self.obstacles = build_town().obstacles() if config.town else None
        self.ai = CrowdAI(config.agents, config.seed, [m.motion for m in self.cast[:self.crowd_cast]], config.ai, config.origin,
                          shares=[s.share for s in specs], obstacles=self.obstacles)
        self.survivor: Survivor | None = None
        self._survivor_layers = np.zeros((1, LAYERS, 4), np.float32)
        self._blows_seen = 0  # the AI's strikes on the player already dealt to the survivor
        if config.survivor:
            self.survivor = Survivor(self._survivor_motion(), self.ai.origin)
            self.ai.player = self.survivor.position.copy()
        # The headless player's circle: through the horde, or in a town round the crossing at the centre, in its streets.
        radius = self.ai.half_extent * 0.5 if self.obstacles is None else min(self.ai.half_extent * 0.5, TOWN_CIRCLE_M)
        self.player_script = PlayerScript(radius) if config.scripted_player else None
        if self.player_script is not None:
            self.player_script.update(self.ai, self.survivor)  # where it starts (time 0: it moves, it strikes nothing yet)
        self.layers = np.empty((config.agents, LAYERS, 4), np.float32)  # this frame's layers, as processed
        started.update(1)
        started.set_description("starting the crowd: the GPU stages")
        self.impostor_notes: list[str] = []  # one line each: what making the atlases said (a rebuilt cache)
        self._make_impostors()
        # Leave out what the scene does not need: no weapons, no socket, or nobody armed → no read-back
        # stage, no gather pass, no weapon meshes, and one palette instead of a ring.
        self.stages = Stages.build(ctx, self._parts(), self._spec(self._armed(config)), self.counts)
        started.update(1)
        self.sync = PaletteSync(self.processor.history, self.rows)
        # The running crowd's foot skate: FOOT_SKATE_SAMPLE agents' foot joints ride on the socket read-back.
        self.foot_skate = FootSkateMonitor(self.character.skeleton, FOOT_SKATE_SAMPLE)
        self._socket_entries: dict[int, int] = {}  # frame -> how many of its gathered entries are weapon sockets
        self.readback_waits = SampleRing()  # ms the CPU waited on each read-back
        self.readback_stalls = 0
        self._pose_lag: deque = deque(maxlen=RING + 1)  # simulated seconds of the last frames
        self.frames = 0
        self.passes_run: list[str] = []
        # Morph weights the panel holds, per character: (M,) weights (-1: not held) and whose (an agent's
        # number among the character's, or crowd.anim.morph.ALL_HELD); handed to each new processor.
        self.morph_holds: dict[int, tuple[np.ndarray, int]] = {}
        self.last = FrameState()
        self.camera = self.default_camera(16 / 9)

    # -- the cast

    @property
    def character(self) -> Character:
        return self.cast[0].character

    @property
    def bake(self) -> AnimationBake:
        return self.cast[0].bake

    @property
    def roles(self) -> dict:
        return self.cast[0].roles

    @property
    def motion(self) -> Motion:
        return self.cast[0].motion

    @property
    def legs(self):
        return self.cast[0].legs

    @property
    def clip_speed(self) -> dict:
        return self.cast[0].clip_speed

    @property
    def role_notes(self) -> list[str]:
        return [note for member in self.cast for note in member.role_notes]

    def _parts(self) -> list[CastPart]:
        return [member.part() for member in self.cast]

    @property
    def counts(self) -> tuple[int, ...]:
        """Agents of each character the stages draw: the crowd's, then 1 for the survivor."""
        return self.ai.cast + ((1,) if self.survivor is not None else ())

    @property
    def rows(self) -> int:
        """Agents the stages draw (the palette's rows of agents): the crowd's and the survivor."""
        return self.ai.n + (1 if self.survivor is not None else 0)

    def _bake(self, k: int, fps, precision: str, bound_mm: float, report=None, morphs: bool | None = None) -> AnimationBake:
        """Character k's bake: the clips its roles play (only those), or the survivor's (crowd.sim.player.ROLES),
        with their morph weight tracks where the scene moves the character's targets (`morphs`: the
        morphs setting, default the config's; each character's variations seeded by its place in the cast)."""
        member = self.cast[k]
        clips = SURVIVOR_ROLES if member.player else clips_used(member.roles)
        clips = [member.character.clip(c) for c in clips]
        joints = bake(member.character.skeleton, clips, fps, precision, bound_mm=bound_mm, report=report)
        if self.config.morphs if morphs is None else morphs:
            try:
                joints.morphs = bake_morphs(member.character, clips, joints, member.spec.morph, self.config.seed + k)
            except MorphError as exc:
                raise PipelineError(f"{member.character.name}: {exc}") from None
        return joints

    def _survivor_motion(self) -> SurvivorMotion:
        member = self.cast[-1]
        return survivor_motion(member.character, member.bake, 0 if member.masks is not None else -1, member.clip_speed)

    def _motion(self, k: int, clip_speed: dict | None = None) -> Motion:
        """Character k's Motion: its baked roles at its playback speeds, its weapons numbered after those
        of the armed characters before it (as the weapon stage numbers them)."""
        member = self.cast[k]
        first = cast_weapons([m.character for m in self.cast])[0][k]
        motion = motion_for(member.character, member.bake, member.roles, member.clip_speed if clip_speed is None else clip_speed)
        return dataclasses.replace(motion, weapon_first=first)

    def member(self, character: int) -> CastMember:
        """The cast's character `character` (an index), or PipelineError."""
        if isinstance(character, bool) or not isinstance(character, (int, np.integer)) or not 0 <= character < len(self.cast):
            raise PipelineError(f"no character {character!r}; the cast has {len(self.cast)}")
        return self.cast[int(character)]

    # -- the stages, built by crowd.stages and owned here

    @property
    def processor(self) -> AnimationProcessor:
        return self.stages.processor

    @property
    def renderer(self) -> CrowdRenderer:
        return self.stages.renderer

    @property
    def readback(self) -> SocketReadback | None:
        return self.stages.readback

    @property
    def weapons(self) -> WeaponRenderer | None:
        return self.stages.weapons

    @property
    def town(self) -> TownRenderer | None:
        return self.stages.town

    @property
    def agents(self) -> int:
        return self.ai.n

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
                         impostor_distance=c.impostor_distance, lod_fade=c.lod_fade, gl_limit=GL_LIMITS[c.gl])

    # -- impostors (crowd.draw.impostors): only where the scene needs them

    def impostors_needed(self) -> bool:
        """Whether the crowd's far agents are drawn as impostors: setting "on", or "auto" with at least
        IMPOSTOR_AGENTS agents (fewer fit as meshes) spread wide enough that the camera framing them all
        has some past the impostor distance."""
        mode = SETTINGS["impostors"].check(self.config.impostors, PipelineError)
        if mode != "auto":
            return mode == "on"
        if self.ai.n < IMPOSTOR_AGENTS:
            return False
        half = self.ai.half_extent
        reach = half * 1.5 + 2.5 + half * math.sqrt(2.0)  # overview_camera's distance, then the farthest corner
        return reach >= self.config.impostor_distance

    def _make_impostors(self, bakes=None) -> bool:
        """Each crowd character's atlas made for its bake (or `bakes`, one per character of the cast, about
        to be used), from the cache where it holds one, or dropped, as the scene needs; True where that
        changed anything (the processor and renderer must then be built again)."""
        from .draw.impostor_bake import load_atlas

        want = self.impostors_needed()
        changed = False
        for member, bake in zip(self.cast[:self.crowd_cast], bakes or [m.bake for m in self.cast]):
            if not want:
                changed |= member.impostor is not None
                member.impostor = None
                continue
            if member.impostor is not None and member.impostor.bake is bake:
                continue
            atlas = load_atlas(self.ctx, member.character, bake, gl_limit=GL_LIMITS[self.config.gl])
            for note in atlas.notes:
                self.impostor_notes.append(f"{member.character.name}: {note}")
                print(f"{member.character.name}: {note}", file=sys.stderr)
            member.impostor = atlas
            changed = True
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
        self._lock_ground = None
        self.sync.reset()
        if self.readback is not None:
            self.readback.reset()

    def set_lod_fade(self, metres: float) -> None:
        """Cross-fade each LOD switch over `metres` (0: switch at once), live."""
        metres = SETTINGS["lod_fade"].check(metres, PipelineError)
        self.renderer.set_lod_fade(metres)
        self.config = dataclasses.replace(self.config, lod_fade=metres)

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

    def set_ai_config(self, config: AIConfig) -> None:
        self.ai.set_config(config)
        self.config = dataclasses.replace(self.config, ai=self.ai.config)

    def rebake(self, fps: float | str, precision: str, interpolation: str | None = None, bound_mm: float | None = None) -> None:
        """Bake the scene's clips again at another rate, precision or compression bound, or process them
        with another interpolation, live: a new bake and processor replace the old ones (released), and
        the crowd keeps its state."""
        self.use_bake(self.make_bake(fps, precision, bound_mm), interpolation)

    def make_bake(self, fps: float | str, precision: str, bound_mm: float | None = None, report=None) -> tuple[AnimationBake, ...]:
        """New bakes of the scene's clips, one per character of the cast (CPU only, no GL: a thread may
        run it while frames go on); `report` is crowd.progress's callback."""
        bound_mm = self.config.compression_bound_mm if bound_mm is None else bound_mm
        return tuple(self._bake(k, fps, precision, bound_mm, report) for k in range(len(self.cast)))

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
        for k, member in enumerate(self.cast[:self.crowd_cast]):
            member.motion = self._motion(k)
            self.ai.set_motion(member.motion, k)
        if self.survivor is not None:
            self.survivor.motion = self._survivor_motion()

    def set_morphs(self, on: bool) -> None:
        """Morph targets drawn (the cast baked again with its weight tracks, the processor writing pairs,
        the draw reading them) or not (none of it exists), live."""
        on = SETTINGS["morphs"].check(on, PipelineError)
        if on == self.config.morphs:
            return
        bakes = tuple(self._bake(k, m.bake.fps, m.bake.precision, m.bake.bound_mm, morphs=on) for k, m in enumerate(self.cast))
        self.use_bake(bakes)
        self.config = dataclasses.replace(self.config, morphs=on)

    def set_processor_path(self, path: str) -> None:
        """Run the same bake on another processor path (compute, fragment or auto), live."""
        path = SETTINGS["processor"].check(path, PipelineError)
        processor = build_processor(self.ctx, self._parts(), dataclasses.replace(self._spec(), processor_path=path), self.counts)
        self.stages.replace("processor", processor)
        self.config = dataclasses.replace(self.config, processor_path=path)
        self._lock_ground = None
        self.sync.reset()
        if self.readback is not None:
            self.readback.reset()

    def set_foot_lock(self, on: bool) -> None:
        """The foot lock on (a processor that holds planted feet, with its state buffers) or off (a
        processor without them, the lock's code compiled out), live; the crowd keeps its state."""
        on = SETTINGS["foot_lock"].check(on, PipelineError)
        processor = build_processor(self.ctx, self._parts(), dataclasses.replace(self._spec(), foot_lock=on), self.counts)
        self.stages.replace("processor", processor)
        self.config = dataclasses.replace(self.config, foot_lock=on)
        self._lock_ground = None
        self.sync.reset()
        if self.readback is not None:
            self.readback.reset()

    def foot_lock_state(self) -> dict:
        """Whether the processor holds feet now, which, and why not where it does not (per character in a
        cast of several: "cast")."""
        held = self.processor.legs
        states = []
        for k, member in enumerate(self.cast):
            if held is not None and held[k] is not None:
                states.append({"on": True, "legs": list(held[k].names)})
                continue
            why = ("off in the scene" if not self.config.foot_lock else "no leg found (an ankle under a knee under a hip)" if not len(member.legs)
                   else "the fragment path has no state to keep it in (it runs on the compute path)")
            states.append({"on": False, "legs": list(member.legs.names), "why": why})
        if len(states) == 1:
            return states[0]
        return {"on": any(s["on"] for s in states), "cast": {m.name: st for m, st in zip(self.cast, states)}}

    def _lock_motion(self) -> np.ndarray:
        """Each agent's ground step since the last run (float64, so a world far from the origin loses
        nothing to float32) and its front times its scale: the foot lock's input, written into arrays
        kept between frames (0.26 ms for 100,000 agents). A new agent, or the first run after the
        processor was made, steps 0; a respawn steps as far as it was moved, which the lock reads as a
        teleport. The survivor's row follows the crowd's."""
        ai, n, rows = self.ai, self.ai.n, self.rows
        last = self._lock_ground
        if last is None or last.shape[1] != rows:
            fresh = np.zeros((2, rows))
            fresh[0, :n], fresh[1, :n] = ai.x, ai.z
            if self.survivor is not None:
                fresh[:, n] = self.survivor.position
            if last is not None:
                keep = min(n, last.shape[1])
                fresh[:, :keep] = last[:, :keep]
            last = self._lock_ground = fresh
            self._lock_motion_rows = np.empty((rows, 4), np.float32)
        motion = self._lock_motion_rows

        def step(lo: int, hi: int) -> None:  # over spans of agents side by side (crowd.spans)
            np.subtract(ai.x[lo:hi], last[0, lo:hi], out=motion[lo:hi, 0], casting="same_kind")
            np.subtract(ai.z[lo:hi], last[1, lo:hi], out=motion[lo:hi, 1], casting="same_kind")
            np.multiply(ai.hx[lo:hi], ai.scale[lo:hi], out=motion[lo:hi, 2], casting="same_kind")
            np.multiply(ai.hz[lo:hi], ai.scale[lo:hi], out=motion[lo:hi, 3], casting="same_kind")
            last[0, lo:hi] = ai.x[lo:hi]
            last[1, lo:hi] = ai.z[lo:hi]

        over_spans(step, n)
        if self.survivor is not None:
            s = self.survivor
            motion[n] = (*(s.position - last[:, n]), *s.heading)
            last[:, n] = s.position
        return motion

    def set_clip_speed(self, name: str, speed: float, character: int = 0) -> None:
        """A clip's playback speed (three.js's timeScale), of one character of the cast. Locomotion clips
        move the zombie faster too, so their feet stay planted; actions end sooner."""
        member = self.member(character)
        member.bake.clip_index(name)
        speeds = {**member.clip_speed, name: float(speed)}
        if int(character) >= self.crowd_cast:  # the survivor's clips: its controller's durations
            SETTINGS["clip_speed"].check(float(speed), PipelineError, f"clip {name!r}")
            member.clip_speed = {k: v for k, v in speeds.items() if v != 1.0}
            self.survivor.motion = self._survivor_motion()
            return
        motion = self._motion(int(character), speeds)  # checks the range
        member.clip_speed = {k: v for k, v in speeds.items() if v != 1.0}
        member.motion = motion
        self.ai.set_motion(motion, int(character))

    def set_clip_loop(self, name: str, loop: bool, character: int = 0) -> None:
        member = self.member(character)
        self.processor.set_clip_loop(member.bake.clip_index(name), loop, int(character))

    def set_agent_count(self, agents: int) -> None:
        agents = SETTINGS["agents"].check(agents, PipelineError)
        before = self.ai.n
        self.ai.resize(agents)
        moves = list(self.ai.moved)  # each character keeps its first agents, at its block's new place
        if self.survivor is not None:
            moves.append((before, agents, 1))  # the survivor's row follows the crowd's
        self.foot_skate.reset()  # (the sample is spread over the new count)
        self.processor.resize(self.counts)
        self.layers = np.empty((agents, LAYERS, 4), np.float32)
        self.sync.resize(self.rows, self.frames, moves)
        if self._lock_ground is not None:
            self._lock_ground = None  # made anew from where everyone stands; a kept agent steps 0 once
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
        self.foot_skate.reset()
        self.processor.reset_lock()  # other agents now: nothing held is theirs
        self._lock_ground = None
        self.sync.spawned(slice(None), self.frames)

    def set_readback_latency(self, latency: int) -> None:
        """1 to 3 frames. The palette ring is reallocated, so weapons are hidden for `latency` frames."""
        self.latency = SETTINGS["readback_latency"].check(latency, PipelineError)
        if self.readback is not None:
            self._set_palette_history(self._spec().history)

    def default_camera(self, aspect: float) -> Camera:
        """What a newcomer sees first: the whole crowd where it fits in VIEW_RADIUS_M (or one agent up
        close), else the player and the horde around it, VIEW_RADIUS_M to each side, receding into the fog
        (the crowd's density does not depend on its size, so the picture does not either). A view of the
        whole of a big crowd showed specks at 10,000 agents and fog or sky at a million."""
        if self.ai.half_extent <= VIEW_RADIUS_M:
            return self.overview_camera(aspect)
        centre = np.array([self.ai.player[0], 0.0, self.ai.player[1]])
        return self._three_quarter(centre, VIEW_RADIUS_M, aspect, FOG_FAR_M, self.obstacles is not None)

    def overview_camera(self, aspect: float) -> Camera:
        """A three-quarter view that frames the whole crowd (or one agent up close): the benchmarks' view,
        which every agent is in."""
        centre = np.array([self.ai.origin[0], 0.0, self.ai.origin[1]])
        return self._three_quarter(centre, max(self.ai.half_extent, 1.2), aspect, 0.0, self.obstacles is not None)

    @staticmethod
    def _three_quarter(centre: np.ndarray, extent: float, aspect: float, far: float, town: bool = False) -> Camera:
        """A view of `centre` from up and to one side, `extent` metres around it in the picture. In a town,
        from above the street that runs along z through the centre (the origin is a crossing), looking down
        it: a diagonal view would look at the buildings' walls and roofs, not at the crowd in the streets."""
        dist = extent * 1.5 + 2.5
        eye = centre + (np.array([0.0, dist * 0.55, dist * 0.9]) if town else np.array([dist * 0.45, dist * 0.5, dist * 0.85]))
        return Camera(eye=eye, target=centre + np.array([0.0, 0.8, 0.0]), aspect=aspect, far=max(200.0, dist * 4, far))

    def _run(self, name: str) -> None:
        if name not in self.passes_run:
            self.passes_run.append(name)

    def block(self, character: int) -> slice:
        """The agents of one character of the cast (each character's are one block, in the cast's order;
        the survivor's, its one row after the crowd's)."""
        self.member(character)
        first = int(sum(self.counts[:character]))
        return slice(first, first + int(self.counts[character]))

    def _block(self, overrides: LayerOverrides) -> slice | None:
        """The agents a forced clip may play on: its character's (None: a crowd of one character)."""
        if overrides.forced is None or len(self.cast) == 1:
            return None
        return self.block(overrides.forced.character)

    def _forced_clip(self, overrides: LayerOverrides) -> tuple[float, float, bool]:
        """(duration, playback speed, loop) of the clip `overrides` forces, for LayerOverrides.apply."""
        if overrides.forced is None:
            return 1.0, 1.0, True
        member = self.member(overrides.forced.character)
        info = member.bake.clips[overrides.forced.clip]
        return info.duration, member.clip_speed.get(info.name, 1.0), info.loop

    def frame(self, framebuffer: moderngl.Framebuffer, dt: float, overrides: LayerOverrides | None = None) -> FrameState:
        """Run one frame into `framebuffer`, the simulation advancing `dt` seconds; `overrides` (the
        panel's forced clips and held weights) go on top of the AI's layers. Returns the frame's state."""
        t = self.timer
        f = self.frames
        if overrides:
            forced = overrides.forced
            overrides.validate(len(self.member(forced.character if forced is not None else 0).bake.clips), LAYERS)
        sim_time, ai_before = self.ai.time, self.ai
        survivor = self.survivor
        with t.cpu("ai"):
            if self.player_script is not None:
                self.player_script.update(self.ai, survivor)
            landed = False
            if survivor is not None:  # the player's character moves first: the zombies chase where it is now
                half = self.ai.half_extent
                landed = survivor.step(dt, (self.ai.origin - half, self.ai.origin + half))
                if self.obstacles is not None:  # it does not walk through walls either
                    survivor.collide(self.ai.keep_out, self.obstacles)
                self.ai.player = survivor.position.copy()
            self.ai.focus = (np.asarray(self.camera.eye, np.float64)[[0, 2]],)  # zombies near the camera think every substep
            steps_before = self.ai.steps
            self.ai.step(dt)
            if survivor is not None:
                steps_before = self._survivor_events(landed, steps_before)
            instances = self.instances()
            self.layers = layers = self.ai.write_layers()  # the AI's own array: no copy (its workers write it)
            if overrides:
                overrides.apply(layers, self.ai.time, *self._forced_clip(overrides), within=self._block(overrides))
            blocks = layers
            if survivor is not None:  # its row after the crowd's: its own block of layers (its instance: instances())
                blocks = [layers, survivor.write_layers(self._survivor_layers)]
        self._run("ai")
        self.sync.spawned(np.flatnonzero(self.ai.spawned_step >= steps_before), f)  # respawned (or added) in this frame's step
        self._pose_lag.append(float(min(dt, self.ai.config.max_dt)))
        read = None
        if self.readback is not None:
            # Before this frame's gather: with N = 3 the slot read now is the one written next.
            with t.cpu("readback"):
                read = self.readback.fetch(f - self.latency)
                if read is not None:
                    read = self._split_feet(read)
            self._run("readback")
            if read is not None:
                self.readback_waits.append(read.wait_ms)
                self.readback_stalls += int(read.stalled)
        with t.cpu("upload"):
            if self.processor.legs is not None:
                # The simulated seconds the frame stepped (a new round's new crowd started its clock anew).
                stepped = self.ai.time - sim_time if self.ai is ai_before else min(float(dt), self.ai.config.max_dt)
                self.processor.upload(blocks, self._lock_motion(), stepped)
            else:
                self.processor.upload(blocks)
        for k, part in enumerate(self.processor.parts):
            if part.held is not None:
                self.processor.hold_morphs(k, *self.morph_holds.get(k, (np.full(len(part.held), -1.0), NOT_HELD)))
        rows = self.rows
        if rows:
            with t.gpu("process"):
                self.processor.run()
            self._run("process")
            if any(part.key for part in self.processor.layout.parts):
                self._run("impostors")  # (the keys in the process pass; the quads in the shadow and draw passes)
            if any(part.morph for part in self.processor.layout.parts):
                self._run("morph_weights")  # (in the process pass; the draws add the deltas: gpu_bytes' "morphs")
            self.sync.processed(f, fresh=self.processor.runs == 1)  # a new palette: the frames kept before it are gone
        weapon_of_agent = self._weapon_of_agent()
        if self.readback is not None and rows:
            armed = self._placed_weapons(weapon_of_agent, instances)  # an impostor's weapon is not placed
            # The sample of the foot-skate measure is the first character's agents (its feet, its block).
            feet, foot_joints = self.foot_skate.entries(self.ai.cast[0], self.ai.steady)
            agents = np.concatenate([armed, feet])
            joints = np.concatenate([self.weapons.socket_joints[weapon_of_agent[armed]], foot_joints])
            if self.readback.gather(f, self.processor, agents, joints, t):
                self._run("gather")
                self._run("transfer")
                self._socket_entries[f] = armed.size
                sampled = feet[:: max(len(self.foot_skate.feet), 1)]
                self.foot_skate.sent(f, sampled, instances.position[sampled][:, [0, 2]], instances.yaw[sampled],
                                     instances.scale[sampled], self.ai.time)
        # Each body's palette: frame F - N where the weapon read-back is from that frame, else this one.
        row_offset = self.sync.row_offsets(None if read is None else read.frame, self.processor.row_offset) if rows else 0
        with t.cpu("cull_lod"):
            # The CPU path culls and packs here; the GPU path packs and uploads every agent's record and
            # then dispatches the cull ("cull": its GPU time; a query around the upload would also count
            # the CPU's copying while the GPU waits for it).
            # The shadow cascades cover the AI's world square (crowd.draw.shadows), known without a pass over the agents.
            half, centre = self.ai.half_extent, self.ai.origin
            top = 0.0 if self.town is None else self.town.height  # (the town's roofs cast shadows into the streets)
            self.renderer.crowd_box = (np.array([centre[0] - half, 0.0, centre[1] - half]), np.array([centre[0] + half, top, centre[1] + half]))
            view = self.renderer.prepare(self.camera, instances, row_offset, cull_now=False, palette=self.processor.layout)
            if self.renderer.culls_on_gpu and rows:
                with t.gpu("cull"):
                    self.renderer.cull(self.processor)
        self._run("cull_lod")
        if self.town is not None:
            with t.cpu("town_cull"):
                self.town.prepare(view)
            self._run("town_cull")
        if self.renderer.culls_on_gpu and rows:
            self._run("cull")
        agent_frames = None
        if self.weapons is not None:
            with t.cpu("attach"):
                agent_frames = AgentFrames(instances.position, instances.yaw, instances.scale, self.camera.eye)
                gpu = self.renderer.gpu
                fallen = ~self.ai.alive() if survivor is None else np.append(~self.ai.alive(), False)
                # (An agent drawn as its impostor alone holds its weapon in its impostor: none placed for it.)
                shown, casting = (view.visible, view.casting) if view.held is None or view.visible is None else \
                    (view.visible & ~view.held, None if view.casting is None else view.casting & ~view.held[None])
                # (the GPU paths' visibility: the compute cull's buffers, or the feedback cull's texture)
                visibility = (gpu.visible, gpu.agents_buffer) if gpu is not None else \
                    self.renderer.feedback.visible if self.renderer.feedback is not None else None
                self.weapons.attach(self.sync.synced(read, rows), agent_frames, weapon_of_agent, shown, visibility, casting, view.lod, fallen=fallen)
            self._run("attach")
        self.last = FrameState(f, view, read, row_offset, agent_frames)
        framebuffer.use()
        framebuffer.clear(*self.renderer.clear_color(), 1.0, depth=1.0)
        if self.renderer.shadows:
            with t.gpu("shadow"):
                self.renderer.shadow_pass(view, self.processor)
                if self.weapons is not None and self.weapons.casts_shadows():
                    self.weapons.depth_pass(view, self.renderer)
                if self.town is not None:
                    self.town.depth_pass(view, self.renderer)
            self._run("shadow")
        if self.renderer.draws_anything(rows):
            with t.gpu("draw"):
                self.renderer.color_pass(framebuffer, view, self.processor)
            self._run("draw")
        if self.weapons is not None and (self.weapons.last["weapons"] or self.weapons.last["dropped"]):
            with t.gpu("weapons"):
                self.weapons.color_pass(framebuffer, view, self.renderer)
            self._run("weapons")
        if self.town is not None:
            with t.gpu("town"):
                self.town.color_pass(framebuffer, view, self.renderer)
            self._run("town")
        with t.gpu("ground"):
            self.renderer.ground_pass(framebuffer, view)
        self._run("ground")
        if self.renderer.pyramid is not None and rows:
            with t.gpu("hiz"):  # the next frame's occlusion test reads this frame's depth
                self.renderer.capture_depth(framebuffer, view)
            self._run("hiz")
        t.end_frame()
        self.frames += 1
        return self.last

    # -- the survivor

    def _placed_weapons(self, weapon_of_agent: np.ndarray, instances: Instances) -> np.ndarray:
        """The agents whose weapons the CPU places this frame: those holding one (a living armed zombie, the
        survivor where it has one) that may be drawn as meshes, which leaves out the agents of characters
        with impostors past the impostor distance and its fade band (with a bounding radius to spare, as
        the cull measures from the sphere's centre): the CPU's work on weapons then grows with the agents
        drawn as meshes, not with the crowd. One pass over spans of the agents side by side (crowd.spans),
        with no gathers: 22 ms a frame at 1,000,000 agents on the H200 host as gathers of the armed ones."""
        ai, n = self.ai, self.ai.n
        impostor_lods = np.asarray(self.renderer.impostor_lods)
        impostors = bool(np.any(impostor_lods >= 0))
        reach = self.renderer.impostor_distance + self.renderer.lod_fade + float(self.renderer.bounds[:, 3].max()) * 2.0
        eye = np.asarray(self.camera.eye, np.float64)
        survivor_kind = len(self.cast) - 1

        def pick(lo: int, hi: int) -> np.ndarray:
            keep = weapon_of_agent[lo:hi] >= 0
            top = min(hi, n)  # (the crowd's rows; the survivor's after them)
            if lo < top:
                keep[:top - lo] &= ai.state[lo:top] < DYING
            if impostors:
                d2 = np.zeros(hi - lo)
                for c in range(3):
                    axis = instances.position[lo:hi, c] - eye[c]
                    d2 += axis * axis
                kind = np.full(hi - lo, survivor_kind, np.int64)
                kind[:max(top - lo, 0)] = ai.kind[lo:top]
                keep &= (d2 <= reach * reach) | (impostor_lods[kind] < 0)
            return np.flatnonzero(keep) + lo

        return np.concatenate(over_spans(pick, len(weapon_of_agent)))

    def _weapon_of_agent(self) -> np.ndarray:
        """Each drawn agent's weapon (-1: none): the crowd's, then the survivor's (its character's first)."""
        if self.survivor is None:
            return self.ai.weapon
        first, _ = cast_weapons([m.character for m in self.cast])
        return np.append(self.ai.weapon, first[-1] if self.cast[-1].character.armed else -1).astype(self.ai.weapon.dtype)

    def instances(self) -> Instances:
        """What the renderer draws this frame: the crowd's instances, and the survivor's after them."""
        s = self.survivor
        crowd = self.ai.instances(extra=0 if s is None else 1)
        variant = dict(crowd.variant)
        held = self._held(len(crowd))
        if held is not None:
            variant[HELD_GROUP] = held
        if s is None:
            return dataclasses.replace(crowd, variant=variant)
        n = self.ai.n
        crowd.position[n] = (s.position[0], 0.0, s.position[1])
        crowd.yaw[n], crowd.scale[n], crowd.tint[n] = np.float32(s.yaw), np.float32(1.0), 255
        if "head" in self.renderer.group_names and "head" not in variant:
            variant["head"] = np.zeros(n + 1, np.int32)
        return Instances(crowd.position, crowd.yaw, crowd.scale, crowd.tint, variant, self.counts)

    def _held(self, rows: int) -> np.ndarray | None:
        """Where impostors hold weapons (crowd.draw.impostors.HELD_GROUP), each drawn agent's choice there:
        0 unarmed (and the survivor's row), else 1 + its weapon among its character's props; None
        without them. Per character block and over spans of agents (crowd.spans): a fancy-indexed
        version took 28 ms a frame at 1,000,000 agents on the H200 host."""
        if HELD_GROUP not in self.renderer.group_names:
            return None
        ai = self.ai
        first, _ = cast_weapons([m.character for m in self.cast])
        firsts = cast_firsts(ai.cast)
        held = np.zeros(rows, np.int32)

        def choose(lo: int, hi: int) -> None:
            for k in range(len(firsts) - 1):
                a, b = max(lo, int(firsts[k])), min(hi, int(firsts[k + 1]))
                if a < b:  # weapon - the character's first + 1 where armed (a living agent with a weapon), else 0
                    armed = (ai.weapon[a:b] >= 0) & (ai.state[a:b] < DYING)
                    np.add(ai.weapon[a:b], 1 - int(first[k]), out=held[a:b], casting="unsafe")
                    np.multiply(held[a:b], armed, out=held[a:b], casting="unsafe")

        over_spans(choose, ai.n)
        return held

    def _survivor_events(self, landed: bool, steps_before: int) -> int:
        """After the crowd's step: the blows the zombies landed on the survivor, its own blow where its
        swing landed (on the nearest zombie within its reach), and a new round where its health ran out.
        Returns the step from which agents count as new (a new round makes them all new)."""
        s, ai = self.survivor, self.ai
        s.hurt(ai.player_hits_taken - self._blows_seen)
        self._blows_seen = ai.player_hits_taken
        if landed:
            target = ai.nearest_alive(s.position, STRIKE_REACH)
            if target >= 0:
                s.kills += ai.hit([target])
        if not s.down:
            return steps_before
        s.new_round(ai.origin)  # the next round: a new crowd, the survivor back in the middle
        self._new_crowd(self.config.seed + s.rounds - 1)
        return 0

    def _split_feet(self, read: SocketRead) -> SocketRead:
        """The weapons' part of a read-back; the foot joints gathered after the sockets go to the foot-skate monitor."""
        sockets = self._socket_entries.pop(read.frame, len(read.agents))
        for old in [k for k in self._socket_entries if k < read.frame]:
            del self._socket_entries[old]
        if sockets == len(read.agents):
            return read
        self.foot_skate.received(read.frame, read.rows[sockets:])
        return dataclasses.replace(read, agents=read.agents[:sockets], joints=read.joints[:sockets], rows=read.rows[:sockets])

    def refresh_counts(self) -> None:
        """Wait for the GPU cull's counts of every queued frame, so ``renderer.last`` and the weapons'
        describe the last frame drawn (the end of a run: stats, benchmarks, tests; never inside a frame)."""
        self.renderer.refresh_counts(wait=True)
        if self.weapons is not None:
            self.weapons.refresh_counts(wait=True)

    def pose_lag_ms(self) -> float:
        """Simulated time the drawn pose trails the simulation by: the last `latency` frames' steps."""
        return round(sum(list(self._pose_lag)[-self.latency:]) * 1e3, 3)

    def weapon_error_mm(self, body: str = "drawn") -> float | None:
        """Largest distance (mm) between a drawn weapon's grip point and its agent's socket point on the
        body, both as the GPU got them (synchronous palette read: tests, stats and benchmarks only).
        body="latest" measures against the newest palette instead: the error of drawing the body
        unsynchronised with the read-back. None when no weapon was drawn."""
        if self.weapons is None or not self.weapons.last["weapons"]:
            return None
        agents, weapon, _ = self.weapons.drawn
        if body == "drawn":
            offsets = np.broadcast_to(np.asarray(self.last.row_offset, np.int64), (self.rows,))[agents]
        else:
            offsets = np.full(len(agents), self.processor.row_offset(0), np.int64)
        rows = self.processor.read_rows(agents, self.weapons.socket_joints[weapon], offsets).astype(np.float64)
        socket_model = np.einsum("kij,kj->ki", rows, self.weapons.socket_bind[weapon][:, :, 3])
        hand = self.last.agent_frames.points(agents, socket_model)
        return float(np.max(np.linalg.norm(hand - self.weapons.grip_points(self.last.agent_frames), axis=1)) * 1e3)

    def project(self, world: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """Pixel (x, y from the top-left) of world points (P, 3) in this frame's camera."""
        rel = np.asarray(world, np.float64) - np.asarray(self.camera.eye, np.float64)
        clip = np.c_[rel, np.ones(len(rel))] @ view_proj(self.camera).astype(np.float64).T
        ndc = clip[:, :3] / clip[:, 3:4]
        return np.stack([(ndc[:, 0] * 0.5 + 0.5) * size[0], (0.5 - ndc[:, 1] * 0.5) * size[1]], axis=1)

    def joint_world_positions(self, joint: int, character: int = 0) -> np.ndarray:
        """World position of one joint of every agent of one character (the first: every agent of a
        crowd of one), from the GPU palette (synchronous; tests, stats)."""
        block = self.block(character)
        pal = self.processor.read_palette()[block]
        skeleton = self.member(character).character.skeleton
        model = palette_joint_positions(pal[:, joint : joint + 1], skeleton.inverse_bind[joint : joint + 1])[:, 0]
        yaw = self.ai.yaw[block]
        c, s = np.cos(yaw), np.sin(yaw)
        rotated = np.stack([c * model[:, 0] + s * model[:, 2], model[:, 1], -s * model[:, 0] + c * model[:, 2]], axis=1)
        ground = np.stack([self.ai.x[block], np.zeros(len(yaw)), self.ai.z[block]], axis=1)
        return ground + self.ai.scale[block, None].astype(np.float64) * rotated

    def gpu_bytes(self) -> dict[str, int]:
        out = dict(self.processor.gpu_bytes())
        out.update(self.renderer.gpu_bytes())
        if self.readback is not None:
            out["readback"] = self.readback.gpu_bytes()
        if self.weapons is not None:
            out["weapons"] = self.weapons.gpu_bytes()
        if self.town is not None:
            out["town"] = self.town.gpu_bytes()
        return out

    def release(self) -> None:
        if self.ai is not None:
            self.ai.close()
        self.timer.release()
        self.stages.release()
