"""The pipeline's crowd when it lives on the GPU (the ai_path setting): the GPU AI (crowd.sim.gpu) beside
the numpy CrowdAI it was made from, which keeps the crowd's scalars (its clock, the player, the world's
size) and spawns each new crowd; the layer buffer the processor copies from; the ring the game's facts
come back through. In a frame the CPU sends the player, the survivor's row and a person's overrides, and
reads back one small copy of counters: nothing per agent.

The rules of a round are crowd.sim.rounds' with two differences the GPU makes: the blows the zombies land
and the kills of the survivor's swings arrive N frames late, with the facts of the frame they happened
in, and a swing's sweep runs on the GPU."""

from __future__ import annotations

import moderngl
import numpy as np

from .draw.gpu_sockets import GpuSocketGather
from .gl import GLObjects, GLStage
from .sim.ai import CrowdAI
from .sim.gpu.ai import COUNTER_WORDS, GpuCrowdAI
from .sim.gpu.facts import FactRing
from .sim.player import STRIKE_REACH, Survivor

LAYER_BYTES = 64  # an agent's four layers


class GpuCrowd(GLStage):
    def __init__(self, ctx: moderngl.Context, ai: CrowdAI, latency: int, fresh: bool = False):
        """`fresh`: `ai` is a crowd just spawned, whose agents the GPU spawns itself (GpuCrowdAI.load)."""
        self.ctx = ctx
        self._objects = GLObjects()
        self.ai = ai
        self.gpu = self._objects.add(GpuCrowdAI(ctx, ai, fresh))
        self._hits_at_load = ai.player_hits_taken
        self.facts = self._objects.add(FactRing(ctx, 4 * COUNTER_WORDS))
        self.latency = int(latency)
        self._layers: moderngl.Buffer | None = None
        self.sockets: GpuSocketGather | None = None  # the weapons' read-back (arm)
        self.last: dict | None = None  # the newest facts read back
        self._kills_seen = 0
        self._picks = 0  # pick requests so far (each answer names its request: crowd.sim.gpu.facts)
        self.sent_bytes = self.read_bytes = 0  # what the last frame sent and read back, for the stats

    def arm(self, socket_joints, far_kinds: list[bool], feet=(), sample: int = 0) -> None:
        """Read the weapons' sockets back from the GPU (the crowd has armed agents and draws weapons), and
        the foot-skate sample's feet with them."""
        if self.sockets is not None and self.sockets.far_kinds != list(far_kinds):  # (new impostors: other characters' far agents)
            self._objects.remove(self.sockets)
            self.sockets.release()
            self.sockets = None
        if self.sockets is None:
            self.sockets = self._objects.add(GpuSocketGather(self.ctx, socket_joints, far_kinds, feet, sample))

    # -- the crowd in and out (a resize, a new crowd, new settings: events, not frames)

    def load(self, ai: CrowdAI, fresh: bool = False) -> None:
        """Take over `ai`'s crowd: a new one (`fresh`: spawned on the GPU from the same draws), or the numpy
        AI after a change made to it (its rows sent)."""
        self.ai = ai
        self.gpu.load(ai, fresh)
        self._hits_at_load = ai.player_hits_taken  # (the GPU counts the blows from 0 again)
        self.facts.forget()  # (the old crowd's totals must not be taken for the new one's: a new round's survivor would take them as blows)
        self.last, self._kills_seen = None, 0

    def store(self) -> CrowdAI:
        """The GPU's crowd written back into the numpy AI (synchronous), which is returned."""
        self.gpu.store(self.ai)
        return self.ai

    # -- a frame

    def step(self, dt: float) -> int:
        """The crowd's step on the GPU, the player where the numpy AI says; its clock follows."""
        g, ai = self.gpu, self.ai
        g.player = np.asarray(ai.player, np.float64).copy()
        g.config, g.half_extent = ai.config, ai.half_extent
        count = g.step(dt)
        ai.time, ai.steps, ai.substeps = g.time, g.steps, g.substeps
        return count

    def layers_buffer(self, size: int) -> moderngl.Buffer:
        if self._layers is None or self._layers.size < size:
            if self._layers is not None:
                self._objects.remove(self._layers)
                self._layers.release()
            self._layers = self._objects.add(self.ctx.buffer(bytes(max(size, 16))))  # (zeros: padded rows weigh nothing)
        return self._layers

    def upload(self, processor, survivor_layers: np.ndarray | None, survivor_motion: np.ndarray | None, overrides, time: float,
               clip: tuple, within, stepped: float) -> None:
        """The processor's input written on the GPU: every agent's layers (and the survivor's row from the
        CPU), a person's overrides on top, the foot lock's motion; then copied into the processor."""
        g = self.gpu
        buffer = self.layers_buffer(processor.layer_bytes())
        g.write_layers(buffer)
        sent = 0
        if survivor_layers is not None:
            buffer.write(np.ascontiguousarray(survivor_layers, np.float32).tobytes(), offset=g.n * LAYER_BYTES)
            sent += survivor_layers.nbytes
        if overrides:
            sent += g.apply_overrides(buffer, overrides, time, clip, within)
        targets = processor.lock_motion_targets()
        if targets:
            g.write_foot_motion(targets)
            if survivor_motion is not None:  # the survivor's own character: the last block, one row
                first, _, lock = targets[-1]
                if first == g.n:
                    lock.write(np.ascontiguousarray(survivor_motion, np.float32).tobytes())
                    sent += survivor_motion.nbytes
        processor.upload_from(buffer, stepped)
        self.sent_bytes = sent

    def read_layers(self, lo: int, hi: int) -> np.ndarray:
        """Agents lo..hi's layers as the processor got them this frame (synchronous: tests, the panel's row)."""
        if self._layers is None or hi <= lo:
            return np.zeros((max(hi - lo, 0), 4, 4), np.float32)
        data = self._layers.read(LAYER_BYTES * (hi - lo), offset=LAYER_BYTES * lo)
        return np.frombuffer(data, np.float32).reshape(hi - lo, 4, 4).copy()

    def capture(self, frame: int, survivor: Survivor | None, selected: int = -1) -> None:
        """The frame's facts into the ring: its state counts, the living near the player (the HUD's), the
        selected agent's row (the panel's), and where the survivor's nearest threat is."""
        if survivor is not None:
            self.gpu.look(survivor.position, 4.0)
        self.gpu.count_states(self.ai.player, self.ai.config.notice_radius, selected)
        self.facts.capture(frame, self.gpu.counters)

    def fetch(self, frame: int) -> dict | None:
        """Frame `frame`'s facts where they are in (F - N: the read-back's latency), without waiting."""
        self.gpu.sent_bytes = 0  # (the frame starts here: its writes from now on)
        facts = self.facts.fetch(frame - self.latency)
        self.read_bytes = self.facts.read_bytes
        if facts is not None:
            self.last = facts
            self.ai.player_hits_taken = self._hits_at_load + facts["blows"]  # (the numpy AI's count: crowd.sim.rounds.settle reads it)
        return facts

    def settle(self, survivor: Survivor, landed: bool, blows_seen: int) -> int:
        """crowd.sim.rounds.settle on the GPU: the blows the facts say landed, the swing's sweep as a GPU
        pass, its kills when their facts come in. Returns the blows seen now."""
        survivor.hurt(self.ai.player_hits_taken - blows_seen)
        if landed:
            self.gpu.sweep(survivor.position, STRIKE_REACH, survivor.heading)
        if self.last is not None and self.last["kills"] > self._kills_seen:
            survivor.kills += self.last["kills"] - self._kills_seen
            self._kills_seen = self.last["kills"]
        return self.ai.player_hits_taken

    # -- what the player's script and the session ask of the crowd (crowd.sim.ai.PlayerScript's interface)

    def nearest_threat(self, point, reach: float) -> np.ndarray | None:
        """Where the nearest living zombie stood, N frames ago (the look ``capture`` asks for each frame)."""
        if self.last is None or self.last["nearest"] < 0:
            return None
        return self.gpu.origin + np.array(self.last["nearest_at"], np.float64)

    def strike_nearest(self, point, reach: float) -> int:
        """Hit the nearest living zombie within reach on the GPU; which one comes back with the facts (-1 now)."""
        self.gpu.strike_nearest(point, reach)
        return -1

    def pick(self, origin, direction, radius: float, height: float) -> int:
        """Ask which agent a ray enters first (crowd.sim.gpu.ai.GpuCrowdAI.pick); returns the request's
        number, whose answer ``picked`` gives once its frame's facts are in."""
        self._picks += 1
        self.gpu.pick(origin, direction, radius, height, self._picks)
        return self._picks

    def picked(self, request: int) -> int | None:
        """The agent pick `request` found (-1: none), or None while its answer is not yet read back."""
        if self.last is None or self.last["picked"][0] != request:
            return None
        return self.last["picked"][1]

    def near_player(self) -> int:
        """Living zombies within notice radius of the player, N frames ago."""
        return 0 if self.last is None else int(self.last["near"])

    def agent_row(self, agent: int) -> dict | None:
        """The selected agent's state N frames ago (crowd.sim.gpu.facts), where it is that agent's."""
        row = None if self.last is None else self.last["selected"]
        if row is None or row["agent"] != agent:
            return None
        return {**row, "x": row["x"] + float(self.gpu.origin[0]), "z": row["z"] + float(self.gpu.origin[1])}

    def counts(self) -> dict:
        """Agents in each state, from the newest facts (every agent wandering before the first arrive)."""
        if self.last is None:
            return {"wander": self.ai.n, "chase": 0, "attack": 0, "hit": 0, "dying": 0, "dead": 0}
        return dict(self.last["states"])

    @property
    def player(self) -> np.ndarray:
        return self.ai.player

    @player.setter
    def player(self, point) -> None:
        self.ai.player = np.asarray(point, np.float64)

    def __getattr__(self, name):  # the crowd's scalars (time, player, origin, config, n, ...) are the numpy AI's
        if name.startswith("_") or name in ("ai", "gpu", "facts"):
            raise AttributeError(name)
        return getattr(self.ai, name)

    def gpu_bytes(self) -> dict:
        out = self.gpu.gpu_bytes()
        out["ai_layers"] = 0 if self._layers is None else self._layers.size
        return out

    def release(self) -> None:
        self._objects.release()
        self._layers = None
