"""One frame of the crowd, stage after stage: ai → read back → upload → process → gather, then the
draw's passes (crowd.frame_passes): cull/LOD → attach → shadow → splat → draw → weapons → ground.

``CrowdPipeline`` owns one instance of each stage and nothing else; each stage owns its GL objects.
The headless smoke mode, the window (through crowd.session) and the benchmarks drive this same class.
Here: building a crowd, the frame's walk and what it reads back. Elsewhere: what the crowd is built from
(crowd.pipeline_config), its characters (crowd.cast), the live setting changes (crowd.live_settings, a
base of the pipeline), the rows of agents each frame draws (crowd.agent_rows) and its default views
(crowd.cameras).

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
import time
from collections import deque

import moderngl
import numpy as np

from . import cameras
from .agent_rows import FootLockSteps, drawn_instances, placed_weapons, weapon_of_agent
from .allocator import keep_freed_memory
from .anim.bake import AnimationBake
from .anim.foot_lock import bake_legs
from .anim.foot_skate import FootSkateMonitor
from .anim.morph import NOT_HELD
from .anim.palette_layout import texel_code
from .anim.palette_reference import palette_joint_positions
from .anim.processor import AnimationProcessor
from .asset.model import Character
from .asset.town import build_town
from .cast import CastMember, bake_member, character_motion, load_cast, player_motion
from .draw.far_agents import FarAgents
from .draw.readback import RING, SocketRead, SocketReadback
from .draw.render import CrowdRenderer, view_proj
from .draw.sync import PaletteSync
from .draw.town import TownRenderer
from .draw.weapons import AgentFrames, WeaponRenderer
from .asset.model import cast_weapons
from .frame import Camera, FrameError, Instances, LayerOverrides, cast_counts
from .gl import GL_LIMITS, GLStage, feature_level, has_compute
from .gpu_crowd import GpuCrowd
from .frame_passes import DRAW_PASSES, FrameState, FrameWork
from .live_settings import LiveSettings
from .pipeline_config import PipelineConfig, PipelineError
from .progress import bar
from .settings import SETTINGS
from .sim.ai import CrowdAI, PlayerScript
from .sim.config import LAYERS
from .sim.motion import Motion
from .sim.player import Survivor
from .sim.rounds import move_survivor, settle
from .stages import CastPart, Stages
from .timing import PassTimer, SampleRing

FOOT_SKATE_SAMPLE = 32  # agents whose feet are read back for the stats' foot_skate: 128 entries beside the sockets


class CrowdPipeline(LiveSettings, GLStage):
    def __init__(self, ctx: moderngl.Context, config: PipelineConfig):
        keep_freed_memory()  # the frame's numpy temporaries reuse memory instead of faulting it in anew (crowd.allocator)
        self.stages = Stages()  # nothing yet: a failure before the build below releases nothing
        self.ai: CrowdAI | None = None  # likewise: its worker processes start with a big enough crowd's first step
        self.gpu_crowd: GpuCrowd | None = None  # the crowd on the GPU (ai_path), beside the numpy AI it was made from
        self.ai_note: str | None = None  # why "auto" left the crowd on the numpy AI (or moved it there)
        # frame -> (the AI's step count when it began, its clock after its step): the GPU path's palette sync
        # (an agent spawned in that frame's step has that spawned_step) and its foot-skate sample
        self._clock_at: dict[int, tuple[int, float]] = {}
        self._crowd_since = 0  # the frame since which the crowd's agents are where they are (a new crowd, a resize)
        self.selected = -1  # the agent the panel follows (its row comes back with the facts on the GPU path)
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
        self.cast: list[CastMember] = load_cast(specs, config.survivor)
        started.update(1)
        started.set_description("starting the crowd: the bake")
        # Leave out what the scene does not need: only the clips the roles play are baked.
        for k, member in enumerate(self.cast):
            member.bake = bake_member(self.cast, k, config.seed, config.bake_fps, config.precision, config.compression_bound_mm,
                                      config.morphs)
            member.legs = bake_legs(member.character.skeleton, member.bake)  # what the foot lock holds, if it runs
        started.update(1)
        started.set_description(f"starting the crowd: {config.agents:,} agents")
        self.lock_steps = FootLockSteps()
        SETTINGS["readback_latency"].check(config.readback_latency, PipelineError)
        self.crowd_cast = len(specs)  # the cast's first characters are the crowd's; a survivor comes after them
        for k in range(self.crowd_cast):
            self.cast[k].motion = character_motion(self.cast, k)
        # The town's obstacles, which the crowd steers around (the town's meshes are the town stage's).
        self.obstacles = build_town().obstacles() if config.town else None
        self.ai = CrowdAI(config.agents, config.seed, [m.motion for m in self.cast[:self.crowd_cast]],
                          self._crowd_ai_config(config.ai, config.survivor), config.origin,
                          shares=[s.share for s in specs], obstacles=self.obstacles)
        self.survivor: Survivor | None = None
        self._survivor_layers = np.zeros((1, LAYERS, 4), np.float32)
        self._blows_seen = 0  # the AI's strikes on the player already dealt to the survivor
        if config.survivor:
            self.survivor = Survivor(player_motion(self.cast[-1]), self.ai.origin)
            self.ai.player = self.survivor.position.copy()
        self.player_script = PlayerScript.headless(self.ai) if config.scripted_player else None
        if self.player_script is not None:
            self.player_script.update(self.ai, self.survivor)  # where it starts (time 0: it moves, it strikes nothing yet)
        self._layers = np.empty((config.agents, LAYERS, 4), np.float32)  # this frame's layers, as processed (the numpy AI's)
        started.update(1)
        started.set_description("starting the crowd: the GPU stages")
        self.impostor_notes: list[str] = []  # one line each: what making the atlases said (a rebuilt cache)
        self._make_impostors()
        # Leave out what the scene does not need: no weapons, no socket, or nobody armed → no read-back
        # stage, no gather pass, no weapon meshes, and one palette instead of a ring.
        self.stages = Stages.build(ctx, self._parts(), self._spec(self._armed(config)), self.counts)
        self._start_gpu_ai(ctx, config)
        started.update(1)
        self.sync = PaletteSync(self.processor.history, self.rows)
        self.far_agents = FarAgents()
        # The running crowd's foot skate: FOOT_SKATE_SAMPLE agents' foot joints ride on the socket read-back.
        self.foot_skate = FootSkateMonitor(self.character.skeleton, FOOT_SKATE_SAMPLE)
        self._socket_entries: dict[int, int] = {}  # frame -> how many of its gathered entries are weapon sockets
        self.readback_waits = SampleRing()  # ms the CPU waited on each read-back
        self.cpu_ms = SampleRing()  # the main thread's CPU ms inside each frame()
        self.readback_stalls = 0
        self._pose_lag: deque = deque(maxlen=RING + 1)  # simulated seconds of the last frames
        self.frames = 0
        self.passes_run: list[str] = []
        # Morph weights the panel holds, per character: (M,) weights (-1: not held) and whose (an agent's
        # number among the character's, or crowd.anim.morph.ALL_HELD); handed to each new processor.
        self.morph_holds: dict[int, tuple[np.ndarray, int]] = {}
        self._holds_applied: dict = {}  # character -> (the processor, its part, the morph_holds entry) last handed to it
        self.last = FrameState()
        self.camera = self.default_camera(16 / 9)

    # -- where the AI runs

    def gpu_ai_refusal(self, ctx: moderngl.Context, config: PipelineConfig) -> str | None:
        """Why the crowd cannot live on the GPU in this pipeline (one line), or None."""
        limit = GL_LIMITS[config.gl]
        if not has_compute(ctx, limit):
            return f"the GPU AI needs GL 4.3 compute shaders, and this context runs GL {feature_level(ctx, limit) / 100:.1f}"
        if self.renderer.cull_path != "gpu":
            return f"the GPU AI's records are packed for the GPU cull path, and this crowd is culled on the {self.renderer.cull_path} path"
        return None

    def _start_gpu_ai(self, ctx: moderngl.Context, config: PipelineConfig) -> None:
        """The crowd on the GPU where the ai_path setting asks for it and it can run: "gpu" refuses a
        pipeline it cannot run in, "auto" falls back to the numpy AI and says why (``ai_note``)."""
        path = SETTINGS["ai_path"].check(config.ai_path, PipelineError)
        why = None if path == "cpu" else self.gpu_ai_refusal(ctx, config)
        if path == "gpu" and why is not None:
            raise PipelineError(f"ai_path gpu: {why}")
        self.ai_note = why if path == "auto" else None
        if path != "cpu" and why is None:
            self.gpu_crowd = GpuCrowd(ctx, self.ai, self.latency, fresh=True)  # (a crowd just spawned: the GPU spawns it too)
            self._records_from_gpu()
            self._survivor_ground = None if self.survivor is None else self.survivor.position.copy()

    def _gpu_path_holds(self) -> bool:
        """Whether the crowd stays on the GPU after the live changes since the last frame: a change it
        cannot run with (the CPU cull path, weapons on) moves it to the numpy AI for good, and says why; a
        new renderer is told to pack its records from the GPU."""
        why = self.gpu_ai_refusal(self.ctx, self.config)
        if why is not None:
            self.gpu_crowd.store()
            self.gpu_crowd.release()
            self.gpu_crowd = None
            self.ai_note = f"moved to the numpy AI: {why}"
            self.lock_steps.reset()
            return False
        self._records_from_gpu()
        if self.weapons is not None:
            self.gpu_crowd.arm(self.weapons.socket_joints, [lod >= 0 for lod in self.renderer.impostor_lods], self.foot_skate.feet,
                               FOOT_SKATE_SAMPLE)
        self.renderer.gpu_record_pass.sent_bytes = 0
        return True

    def _records_from_gpu(self) -> None:
        """The renderer (a new one after a live change too) packs its records from the GPU's crowd."""
        if self.renderer.gpu_record_pass is None:
            self.renderer.gpu_records(cast_weapons([m.character for m in self.cast[:self.crowd_cast]])[0])

    @property
    def ai_path(self) -> str:
        return "cpu" if self.gpu_crowd is None else "gpu"

    @property
    def crowd_ai(self):
        """The crowd the player's script and the session act on: the numpy AI, or the GPU's (crowd.gpu_crowd)."""
        return self.ai if self.gpu_crowd is None else self.gpu_crowd

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

    # -- views

    def default_camera(self, aspect: float) -> Camera:
        """What a newcomer sees first: the "auto" view (crowd.cameras.view_camera), in this crowd."""
        return self.view_camera("auto", aspect)

    def view_camera(self, view: str, aspect: float) -> Camera:
        """A named view of this crowd: "auto", "player", "horizon" or "overview" (crowd.cameras.view_camera)."""
        return cameras.view_camera(view, self.ai, aspect, self.obstacles is not None)

    def overview_camera(self, aspect: float) -> Camera:
        """The three-quarter view that frames the whole crowd (crowd.cameras.overview_camera)."""
        return cameras.overview_camera(self.ai, aspect, self.obstacles is not None)

    # -- the frame

    def note_pass(self, name: str) -> None:
        """Name a pass in passes_run (once)."""
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
        panel's forced clips and held weights) go on top of the AI's layers. Returns the frame's state.
        The main thread's CPU time in it goes to ``cpu_ms`` (waits on the GPU or the OS are not in it)."""
        start = time.thread_time()
        try:
            return self._frame(framebuffer, dt, overrides)
        finally:
            self.cpu_ms.append((time.thread_time() - start) * 1e3)

    def _frame(self, framebuffer: moderngl.Framebuffer, dt: float, overrides: LayerOverrides | None) -> FrameState:
        """The crowd's step (ai → read back → upload → process → gather), on the GPU or with the numpy AI,
        then the draw's passes (crowd.frame_passes.DRAW_PASSES)."""
        if overrides:
            forced = overrides.forced
            overrides.validate(len(self.member(forced.character if forced is not None else 0).bake.clips), LAYERS)
        step = self._step_on_gpu if self.gpu_crowd is not None and self._gpu_path_holds() else self._step
        return self._draw(step(framebuffer, dt, overrides))

    def _step(self, framebuffer: moderngl.Framebuffer, dt: float, overrides: LayerOverrides | None) -> FrameWork:
        """The numpy AI's step, the weapons' read-back, the layers' upload, the processor's pass and the
        sockets' gather."""
        t, f = self.timer, self.frames
        sim_time, ai_before = self.ai.time, self.ai
        survivor = self.survivor
        with t.cpu("ai"):
            if self.player_script is not None:
                self.player_script.update(self.ai, survivor)
            landed = False
            if survivor is not None:  # the player's character moves first: the zombies chase where it is now
                landed = move_survivor(self.ai, survivor, dt, self.obstacles)
            self.ai.focus = (np.asarray(self.camera.eye, np.float64)[[0, 2]],)  # zombies near the camera think every substep
            steps_before = self.ai.steps
            self.ai.step(dt)
            if survivor is not None:
                steps_before = self._survivor_events(landed, steps_before)
            instances = self.instances()
            self._layers = layers = self.ai.write_layers()  # the AI's own array: no copy (its workers write it)
            if overrides:
                overrides.apply(layers, self.ai.time, *self._forced_clip(overrides), within=self._block(overrides))
            blocks = layers
            if survivor is not None:  # its row after the crowd's: its own block of layers (its instance: instances())
                blocks = [layers, survivor.write_layers(self._survivor_layers)]
        self.note_pass("ai")
        self.sync.spawned(np.flatnonzero(self.ai.spawned_step >= steps_before), f)  # respawned (or added) in this frame's step
        self._pose_lag.append(float(min(dt, self.ai.config.max_dt)))
        read = None
        if self.readback is not None:
            # Before this frame's gather: with N = 3 the slot read now is the one written next.
            with t.cpu("readback"):
                read = self.readback.fetch(f - self.latency)
                if read is not None:
                    read = self._split_feet(read)
            self.note_pass("readback")
            if read is not None:
                self.readback_waits.append(read.wait_ms)
                self.readback_stalls += int(read.stalled)
        with t.cpu("upload"):
            if self.processor.legs is not None:
                # The simulated seconds the frame stepped (a new round's new crowd started its clock anew).
                stepped = self.ai.time - sim_time if self.ai is ai_before else min(float(dt), self.ai.config.max_dt)
                self.processor.upload(blocks, self.lock_steps.since_last_run(self.ai, survivor, self.rows), stepped)
            else:
                self.processor.upload(blocks)
        self._process(f)
        rows = self.rows
        agent_weapon = weapon_of_agent(self.ai, [m.character for m in self.cast], survivor)
        if self.readback is not None and rows:
            armed = placed_weapons(self.ai, self.renderer, self.camera.eye, agent_weapon, instances, len(self.cast) - 1)  # an impostor's weapon is not placed
            # The sample of the foot-skate measure is the first character's agents (its feet, its block).
            feet, foot_joints = self.foot_skate.entries(self.ai.cast[0], self.ai.steady)
            agents = np.concatenate([armed, feet])
            joints = np.concatenate([self.weapons.socket_joints[agent_weapon[armed]], foot_joints])
            if self.readback.gather(f, self.processor, agents, joints, t):
                self.note_pass("gather")
                self.note_pass("transfer")
                self._socket_entries[f] = armed.size
                sampled = feet[:: max(len(self.foot_skate.feet), 1)]
                self.foot_skate.sent(f, sampled, instances.position[sampled][:, [0, 2]], instances.yaw[sampled],
                                     instances.scale[sampled], self.ai.time)
        # Each body's palette: frame F - N where the weapon read-back is from that frame, else this one.
        row_offset = self.sync.row_offsets(None if read is None else read.frame, self.processor.row_offset) if rows else 0
        return FrameWork(framebuffer, f, instances, row_offset, read, agent_weapon)

    def _process(self, f: int) -> None:
        """The processor's pass over this frame's uploaded input (with the morph weights the panel holds)."""
        t = self.timer
        for k, part in enumerate(self.processor.parts):
            entry, applied = self.morph_holds.get(k), self._holds_applied.get(k, (None, None, None))
            if part.held is not None and (applied[0] is not self.processor or applied[1] is not part or applied[2] is not entry):
                self.processor.hold_morphs(k, *(entry or (np.full(len(part.held), -1.0), NOT_HELD)))
                self._holds_applied[k] = (self.processor, part, entry)  # (a hold set is a new tuple)
        rows = self.rows
        if rows:
            with t.gpu("process"):
                self.processor.run()
            self.note_pass("process")
            if any(part.key for part in self.processor.layout.parts):
                self.note_pass("impostors")  # (the keys in the process pass; the quads in the shadow and draw passes)
            if any(part.morph for part in self.processor.layout.parts):
                self.note_pass("morph_weights")  # (in the process pass; the draws add the deltas: gpu_bytes' "morphs")
            self.sync.processed(f, fresh=self.processor.runs == 1)  # a new palette: the frames kept before it are gone

    def _step_on_gpu(self, framebuffer: moderngl.Framebuffer, dt: float, overrides: LayerOverrides | None) -> FrameWork:
        """``_step`` with the crowd on the GPU (crowd.gpu_crowd): the player, the survivor's row and a
        person's overrides go in, the facts of frame F - N come back, and every agent's step, layers,
        foot-lock motion and record are written on the GPU."""
        t, f, survivor, crowd = self.timer, self.frames, self.survivor, self.gpu_crowd
        sim_time, ai_before = self.ai.time, self.ai
        steps_before = self.ai.steps
        with t.cpu("ai"):
            crowd.fetch(f)
        read, fallen = self._fetch_sockets(f, crowd)
        with t.cpu("ai"):
            if self.player_script is not None:
                self.player_script.update(crowd, survivor)
            landed = move_survivor(self.ai, survivor, dt, self.obstacles) if survivor is not None else False
            with t.gpu("step"):  # the AI's compute passes (its CPU share is in "ai")
                crowd.step(dt)
            if survivor is not None:
                self._blows_seen = crowd.settle(survivor, landed, self._blows_seen)
                if survivor.down:
                    survivor.new_round(self.ai.origin)
                    self._new_crowd(self.config.seed + survivor.rounds - 1)
                    crowd = self.gpu_crowd
            crowd.capture(f, survivor, self.selected)
        self._clock_at[f] = (steps_before if self.ai is ai_before else 0, self.ai.time)  # (a new round's crowd began at step 0)
        for old in [k for k in self._clock_at if k < f - RING]:
            del self._clock_at[old]
        self.note_pass("ai")
        self._pose_lag.append(float(min(dt, self.ai.config.max_dt)))
        with t.cpu("upload"):
            stepped = self.ai.time - sim_time if self.ai is ai_before else min(float(dt), self.ai.config.max_dt)
            layers = motion = None
            if survivor is not None:
                layers = survivor.write_layers(self._survivor_layers)
                if self.processor.legs is not None:
                    motion = np.array([[*(survivor.position - self._survivor_ground), *survivor.heading]], np.float32)
                    self._survivor_ground = survivor.position.copy()
            clip, within = (self._forced_clip(overrides), self._block(overrides)) if overrides else ((1.0, 1.0, True), None)
            with t.gpu("layers"):  # every agent's layers written into the buffer the processor reads
                crowd.upload(self.processor, layers, motion, overrides, self.ai.time, clip, within, stepped)
        extra = None
        if survivor is not None:
            extra = Instances(np.array([[survivor.position[0], 0.0, survivor.position[1]]]), np.array([survivor.yaw], np.float32),
                              np.ones(1, np.float32), np.full((1, 4), 255, np.uint8), {})
        sim = crowd.gpu.frame_output(extra)
        self._far_keys(crowd, sim, dt)
        self._process(f)
        rows = self.rows
        latest = self.processor.row_offset(0) if rows else 0
        row_offset, agent_weapon = (latest, latest, -1), None
        if self.weapons is not None and crowd.sockets is not None and rows:
            agent_weapon = weapon_of_agent(self.ai, [m.character for m in self.cast], survivor)  # (a trait: the numpy AI's array holds it)
            self._gather_sockets(f, sim, crowd, survivor, agent_weapon)
            age = None if read is None else self.sync.age(read.frame)
            if age is not None:  # each body from the read-back's palette, but agents born after it from this frame's
                row_offset = (self.processor.row_offset(age), latest, self._clock_at[read.frame][0])
        return FrameWork(framebuffer, f, sim, row_offset, read, agent_weapon, fallen)

    def _far_keys(self, crowd, sim, dt: float) -> None:
        """Agents drawn only as impostors get their key alone from this frame's processor run; a cut
        (crowd.draw.far_agents) drops the kept palettes first."""
        r = self.renderer
        if not any(part.key for part in self.processor.layout.parts) or self.processor.path != "compute":
            return
        offset = float(np.linalg.norm(r.bounds[:, :3], axis=1).max()) * sim.max_scale
        beyond = self.far_agents.beyond(r.impostor_distance, r.lod_fade, offset)
        top_speed = max(m.run_speed for m in self.ai.motions) * self.ai.config.speed_max * 1.5  # (pushes besides the gait)
        eye = np.asarray(self.camera.eye, np.float64)
        if self.far_agents.cut(eye, beyond, top_speed * min(float(dt), self.ai.config.max_dt)):
            self.sync.reset()
        # An armed character's impostor holds its weapon on its socket joint (crowd.draw.impostors.held_pieces).
        kept = [[next(iter(m.character.sockets.values()))] if m.character.armed else None for m in self.cast]
        self.processor.key_alone_beyond(crowd.gpu.places, crowd.gpu.looks, eye - np.array([crowd.gpu.origin[0], 0.0, crowd.gpu.origin[1]]),
                                        beyond, self.ai.n, kept)

    def _fetch_sockets(self, f: int, crowd) -> tuple:
        """Frame F - N's weapon sockets (and who was down then) with the crowd on the GPU, read first in the
        frame as the numpy path reads its own: (read or None, the agents down, as a flag per row)."""
        if self.weapons is None or crowd.sockets is None:
            return None, None
        with self.timer.cpu("readback"):
            got = crowd.sockets.fetch(f - self.latency)
            if got is not None and got[0].frame < self._crowd_since:  # gathered from a crowd since replaced or resized
                got = None
        self.note_pass("readback")
        read, down, feet = (None, None, None) if got is None else got
        if read is not None:
            self.readback_waits.append(read.wait_ms)
        if feet is not None:  # the sample's feet, composed with where their agents stood in that frame
            agents, motion, heading, rows = feet
            self.foot_skate.walking(agents)
            ground = motion[:, :2].astype(np.float64) + self.ai.origin
            self.foot_skate.sent(read.frame, agents, ground, np.arctan2(heading[:, 0], heading[:, 1]), heading[:, 3], self._clock_at.get(read.frame, (0, 0.0))[1])
            self.foot_skate.received(read.frame, rows)
        fallen = np.zeros(self.rows, bool)
        if down is not None:
            fallen[down[down < self.rows]] = True
        return read, fallen

    def _gather_sockets(self, f: int, sim, crowd, survivor, weapon: np.ndarray) -> None:
        """This frame's socket gather queued (crowd.draw.gpu_sockets), after the processor's pass; `weapon`:
        each row's weapon (crowd.agent_rows.weapon_of_agent)."""
        texel_base = self.renderer.gpu_record_pass.texel_base(self.processor.layout, self.ai.n)
        extra = None
        if survivor is not None and weapon[-1] >= 0:
            x, y = self.processor.layout.texel(np.array([self.ai.n]), 0, self.processor.row_offset(0))
            extra = (int(weapon[-1]), int(texel_code(x, y)[0]))
        reach = self.renderer.impostor_distance + self.renderer.lod_fade + float(self.renderer.bounds[:, 3].max()) * 2.0
        sampled = self.foot_skate.sampled(self.ai.cast[0])  # (the first character's agents, as on the numpy path)
        with self.timer.gpu("gather"):
            crowd.sockets.gather(f, sim, self.processor, texel_base, int(texel_code(0, self.processor.row_offset(0))), self.camera.eye,
                                 reach, extra, sampled)
        self.note_pass("gather")

    def _draw(self, w: FrameWork) -> FrameState:
        """The frame after its processor pass: DRAW_PASSES, each run where the scene needs it, timed on
        its clock and named in ``passes_run``."""
        for step in DRAW_PASSES:
            if not step.needed(self, w):
                continue
            if step.clock is None:
                step.run(self, w)
                continue
            with (self.timer.gpu if step.clock == "gpu" else self.timer.cpu)(step.name):
                step.run(self, w)
            self.note_pass(step.name)
        self.timer.end_frame()
        self.frames += 1
        return self.last

    def instances(self) -> Instances:
        """What the renderer draws this frame: the crowd's instances, and the survivor's after them."""
        return drawn_instances(self.ai, self.survivor, [m.character for m in self.cast], self.renderer.group_names, self.counts)

    # -- the survivor and the read-back

    def _survivor_events(self, landed: bool, steps_before: int) -> int:
        """After the crowd's step: the blows the zombies landed on the survivor, its own blow where its
        swing landed (on the nearest zombie within its reach), and a new round where its health ran out.
        Returns the step from which agents count as new (a new round makes them all new)."""
        s, ai = self.survivor, self.ai
        self._blows_seen = settle(ai, s, landed, self._blows_seen)
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

    # -- what the running crowd reports (stats, benchmarks, tests)

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
        offset = self.last.row_offset
        if self.gpu_crowd is not None:  # (a crowd on the GPU read back whole: tests and stats only)
            slot, latest, limit = offset
            born = np.append(self.gpu_crowd.store().spawned_step, 0)[: self.rows]
            offset = np.where((limit >= 0) & (born > limit), latest, slot)
        if body == "drawn":
            offsets = np.broadcast_to(np.asarray(offset, np.int64), (self.rows,))[agents]
        else:
            offsets = np.full(len(agents), self.processor.row_offset(0), np.int64)
        rows = self.processor.read_rows(agents, self.weapons.socket_joints[weapon], offsets).astype(np.float64)
        socket_model = np.einsum("kij,kj->ki", rows, self.weapons.socket_bind[weapon][:, :, 3])
        frames = self.last.agent_frames
        if frames is None and self.gpu_crowd is not None:
            drawn = self.instances()
            frames = AgentFrames(drawn.position, drawn.yaw, drawn.scale, self.camera.eye)
        hand = frames.points(agents, socket_model)
        return float(np.max(np.linalg.norm(hand - self.weapons.grip_points(frames), axis=1)) * 1e3)

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

    @property
    def layers(self) -> np.ndarray:
        """The crowd's layers as this frame processed them (N, 4, 4); a crowd on the GPU reads them back,
        waiting for the GPU (tests, stats: never in a frame; the panel reads one row, ``layer_row``)."""
        if self.gpu_crowd is None:
            return self._layers
        return self.gpu_crowd.read_layers(0, self.ai.n)

    @layers.setter
    def layers(self, value: np.ndarray) -> None:
        self._layers = value

    def layer_row(self, agent: int) -> np.ndarray:
        """One agent's layers as this frame processed them (4, 4)."""
        if self.gpu_crowd is None:
            return self._layers[agent]
        return self.gpu_crowd.read_layers(agent, agent + 1)[0]

    def frame_bytes(self) -> dict[str, int]:
        """Bytes the CPU sent to the GPU and read back in the last frame for its agents: on the GPU AI path
        every write and read it makes (the survivor's row, overrides, counters, a blow's list); on the
        numpy path the per-agent ones (layers, records, the foot lock's motion; the lists too on the CPU
        cull path: not counted), and the weapons' read-back."""
        if self.gpu_crowd is not None:
            c = self.gpu_crowd
            sockets = (c.sockets.sent_bytes, c.sockets.read_bytes) if c.sockets is not None and self.weapons is not None else (0, 0)
            return {"upload_bytes": c.sent_bytes + c.gpu.sent_bytes + self.renderer.gpu_record_pass.sent_bytes + sockets[0],
                    "readback_bytes": c.read_bytes + sockets[1]}
        rows = self.rows
        lock = 16 * rows if self.processor.legs is not None else 0
        read = self.last.read
        return {"upload_bytes": 64 * rows + 32 * rows + lock, "readback_bytes": 0 if read is None else int(read.rows.nbytes)}

    def gpu_bytes(self) -> dict[str, int]:
        out = dict(self.processor.gpu_bytes())
        if self.gpu_crowd is not None:
            out.update(self.gpu_crowd.gpu_bytes())
        out.update(self.renderer.gpu_bytes())
        if self.readback is not None:
            out["readback"] = self.readback.gpu_bytes()
        if self.weapons is not None:
            out["weapons"] = self.weapons.gpu_bytes()
        if self.town is not None:
            out["town"] = self.town.gpu_bytes()
        return out

    def release(self) -> None:
        if self.gpu_crowd is not None:
            self.gpu_crowd.release()
        if self.ai is not None:
            self.ai.close()
        self.timer.release()
        self.stages.release()

