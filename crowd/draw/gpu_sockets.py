"""The weapons' socket read-back for a crowd that lives on the GPU (shaders/socket_gather.comp.glsl):
the twin of crowd.draw.readback.SocketReadback with the list of sockets made on the GPU, since the CPU
no longer knows who is armed, alive and near. A compute pass appends each armed agent that may be drawn
as a mesh, with its socket's skinning rows, to this frame's slot of a ring of RING buffers behind a
fence; N frames later the CPU reads the slot's count, then that many entries, without waiting. A slot
holds `capacity` entries; a frame that found more grows the ring for the frames after it (those
weapons are hidden for N frames, never drawn wrong)."""

from __future__ import annotations

import time

import moderngl
import numpy as np

from ..frame import SimFrame
from ..gl import FencedSlots, GLObjects, GLStage, has_uniform, load_shader
from ..sim.gpu.state import FIELDS
from .readback import RING, SocketRead

GROUP = 256
TEXEL_BASE, GATHERED = 17, 19
ENTRY_DTYPE = np.dtype([("who", "<u4", 4), ("rows", "<f4", (3, 4))])
HEADER = 16
FIRST_CAPACITY = 1024
FRAME_ENTRY, FOOT_ENTRY = 0xFFFFFFFF, 0xFFFF0000  # an entry's weapon word when it is a sampled agent's frame, or its foot joint k


class GpuSocketGather(GLStage):
    def __init__(self, ctx: moderngl.Context, socket_joints: np.ndarray, far_kinds: list[bool], feet=(), sample: int = 0,
                 palette_unit: int = 0):
        """`feet`: the foot joints of the foot-skate sample (crowd.anim.foot_skate), of up to `sample` agents
        a frame (none: no feet gathered)."""
        self.ctx = ctx
        self._objects = GLObjects()
        self.socket_joints = np.asarray(socket_joints, np.int32)
        self.far_kinds = list(far_kinds)
        self.feet = list(feet) if sample else []
        self.sample = int(sample) if self.feet else 0
        defines = {"WEAPONS": max(len(self.socket_joints), 1), "KINDS": max(len(self.far_kinds), 1),
                   **({"FEET": len(self.feet), "SAMPLE": self.sample} if self.feet else {})}
        self.program = self._objects.add(ctx.compute_shader(load_shader("socket_gather.comp.glsl", defines)))
        if self.feet:
            self.program["u_feet"].write(np.asarray(self.feet, np.int32).tobytes())
        self.program["u_socket"].write(np.resize(self.socket_joints, max(len(self.socket_joints), 1)).astype(np.int32).tobytes())
        self.program["u_far"].write(np.resize(np.asarray(self.far_kinds, np.int32), max(len(self.far_kinds), 1)).tobytes())
        for plane in range(3):
            self.program[f"u_palette{plane}"] = palette_unit + plane
        self._unit = palette_unit
        self.capacity = 0
        self._slots: list[moderngl.Buffer] = []
        self._done = FencedSlots(RING)
        self._grow(FIRST_CAPACITY)
        self.sent_bytes = self.read_bytes = 0
        self.last_count = 0

    def _grow(self, capacity: int) -> None:
        for buffer in self._slots:
            self._objects.remove(buffer)
            buffer.release()
        for buffer in getattr(self, "_staging", []):
            self._objects.remove(buffer)
            buffer.release()
        self.capacity = int(capacity)
        size = HEADER + ENTRY_DTYPE.itemsize * self.capacity
        self._slots = [self._objects.add(self.ctx.buffer(reserve=size)) for _ in range(RING)]
        # What the CPU maps: copies in buffers the driver keeps where the CPU reads them without waiting
        # (mapping the compute pass's own buffer waited for the whole queue ahead: 5 to 7 ms a frame).
        self._staging = [self._objects.add(self.ctx.buffer(reserve=size, dynamic=True)) for _ in range(RING)]
        self._done.forget()

    def gather(self, frame: int, sim: SimFrame, processor, texel_base: moderngl.Buffer, row_code: int, eye: np.ndarray,
               reach: float, extra: tuple[int, int] | None, sampled: np.ndarray | None = None) -> None:
        """Queue frame `frame`'s gather: `sim`'s armed agents within `reach` metres of `eye` (float64 world)
        where their character has impostors, every one where it has none; `row_code` the texel code of
        this frame's palette slot; `extra` (weapon, joint 0's texel code) of the survivor's row; `sampled`:
        the foot-skate sample's agents this frame (those in steady locomotion send their feet)."""
        k = frame % RING
        slot = self._slots[k]
        slot.write(bytes(HEADER))
        self.sent_bytes = HEADER
        for name in ("motion", "heading", "codes", "looks"):
            sim.buffers[name].bind_to_storage_buffer(FIELDS[name][0])
        texel_base.bind_to_storage_buffer(TEXEL_BASE)
        slot.bind_to_storage_buffer(GATHERED)
        processor.bind_palette(self._unit, self.program)
        rel = np.asarray(eye, np.float64) - np.array([sim.origin[0], 0.0, sim.origin[1]])
        p = self.program
        for name, value in (("u_n", sim.agents), ("u_capacity", self.capacity), ("u_row_code", int(row_code)),
                            ("u_eye", tuple(float(v) for v in rel)), ("u_reach2", float(reach) ** 2),
                            ("u_extra_weapon", -1 if extra is None else int(extra[0])), ("u_extra_code", 0 if extra is None else int(extra[1]))):
            if has_uniform(p, name):
                p[name] = value
        samples = 0
        if self.feet and sampled is not None and len(sampled):
            samples = min(len(sampled), self.sample)
            p["u_sample"].write(np.resize(np.asarray(sampled[:samples], np.int32), self.sample).tobytes())
        if has_uniform(p, "u_samples"):
            p["u_samples"] = samples
        p.run((sim.agents + 1 + samples + GROUP - 1) // GROUP)
        self.ctx.memory_barrier(0x2000 | 0x200)  # (storage writes, then a buffer copy of them)
        self.ctx.copy_buffer(self._staging[k], slot)
        self._done.mark(frame)

    def fetch(self, frame: int) -> tuple[SocketRead, np.ndarray, tuple | None] | None:
        """Frame `frame`'s read-back, sorted by agent (the atomics' order is not the same twice), the
        agents it found down (dying or dead, their weapon for the ground), and the foot-skate sample's
        (agents, (k, 4) motion, (k, 4) heading, (k x feet, 3, 4) foot rows), those in steady locomotion,
        or None; None where that frame's slot is not done, was overwritten or was never gathered. Never
        waits."""
        self.read_bytes = 0
        if not self._done.ready(frame):
            return None
        started = time.perf_counter()
        slot = self._staging[frame % RING]
        count = int(np.frombuffer(slot.read(4), np.uint32)[0])
        self.last_count = count
        if count > self.capacity:  # more than a slot holds: this frame's weapons are hidden, the next ones fit
            self._grow(min(2 * count, 1 << 24))
            return None
        entries = np.frombuffer(slot.read(ENTRY_DTYPE.itemsize * count, offset=HEADER), ENTRY_DTYPE) if count else np.zeros(0, ENTRY_DTYPE)
        self.read_bytes = 4 + entries.nbytes
        kind = entries["who"][:, 1]
        feet = None
        if self.feet:
            frames, foot = entries[kind == FRAME_ENTRY], entries[(kind >= FOOT_ENTRY) & (kind != FRAME_ENTRY)]
            frames = frames[np.argsort(frames["who"][:, 0], kind="stable")]
            foot = foot[np.lexsort((foot["who"][:, 1], foot["who"][:, 0]))]  # by agent, then foot joint
            feet = (frames["who"][:, 0].astype(np.int64), frames["rows"][:, 0].copy(), frames["rows"][:, 1].copy(), foot["rows"].copy())
            entries = entries[kind < FOOT_ENTRY]
        entries = entries[np.argsort(entries["who"][:, 0], kind="stable")]
        who = entries["who"].astype(np.int64)
        down = who[:, 2] >= 4  # (crowd.sim.config.DYING)
        up = ~down
        weapons = who[up, 1]
        read = SocketRead(frame, who[up, 0], self.socket_joints[weapons].astype(np.int64), entries["rows"][up].copy(), 0.0,
                          (time.perf_counter() - started) * 1e3, False, born=who[up, 3])
        return read, who[down, 0], feet

    def gpu_bytes(self) -> int:
        return self._objects.gpu_bytes()

    def release(self) -> None:
        self._done.release()
        self._objects.release()
        self._slots = []
