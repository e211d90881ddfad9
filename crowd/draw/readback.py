"""Read-back stage: the socket joints of armed agents, from the GPU palette to the CPU, without a stall.

Contract:
- ``gather(frame, processor, agents, joints)``, once per frame after the processor has run: a draw
  copies the skinning matrix of each (agent, socket joint) pair out of the palette the processor has
  just written into one compact RGBA32F texture, and one glReadPixels moves it into the frame's
  pixel-pack buffer (PBO) of a ring of RING. Both are queued GPU commands; the CPU does not wait.
  A fence marks the end of the transfer.
- ``fetch(frame)``, N frames later (N = 1 to RING, the latency): the entries of that frame and their
  (M, 3, 4) float32 matrix rows. Reading waits only if the GPU has not finished that frame's transfer:
  with N >= 1 it never waits on the frame just submitted, and the time it waits is recorded
  (``wait_ms``; ``stalls`` counts the reads that found the fence unsignaled).
- A frame whose slot has been overwritten, or was never gathered, gives None: the caller hides its
  weapons (the first N frames, or after the palette has been reallocated).
- No armed agent in a frame: no gather draw, no transfer, an empty read.

The stage exists only when a scene has armed agents: without it there is no gather texture, no ring
of buffers and no pass (see CrowdPipeline).
"""

from __future__ import annotations

import math
import time
from contextlib import nullcontext
from dataclasses import dataclass

import moderngl
import numpy as np

from ..errors import CrowdError
from ..gl import Fence, GLStage, gpu_bytes, load_shader
from ..settings import SETTINGS
from ..anim.palette_layout import texel_code

RING = SETTINGS["readback_latency"].high  # one slot per frame of the longest read-back latency
ENTRIES_PER_ROW = 1024  # gather texture: 3 x 1024 texels wide, one row per 1,024 entries
ENTRY_BYTES = 3 * 4 * 4  # three RGBA32F texels


class ReadbackError(CrowdError, ValueError):
    """Bad read-back input; the message is one line."""


@dataclass
class SocketRead:
    """What the CPU got back for one frame: entry k is socket joint ``joints[k]`` of agent ``agents[k]``."""

    frame: int
    agents: np.ndarray  # int64 (M,)
    joints: np.ndarray  # int64 (M,)
    rows: np.ndarray  # float32 (M, 3, 4): rows of the socket's skinning matrix (joint world x inverse bind)
    wait_ms: float  # time blocked on the fence
    copy_ms: float  # time mapping the buffer and copying it out
    stalled: bool  # the transfer had not finished when the CPU came to read it
    born: np.ndarray | None = None  # a crowd on the GPU: each entry's spawn step (crowd.draw.gpu_sockets)


@dataclass
class _Slot:
    frame: int = -1
    agents: np.ndarray | None = None
    joints: np.ndarray | None = None
    fence: Fence | None = None


class SocketReadback(GLStage):
    """Owns the gather program, the entry and gather textures and the ring of pixel-pack buffers."""

    def __init__(self, ctx: moderngl.Context):
        # What release() walks, first: a constructor that fails later still releases cleanly.
        self.program = self._vao = None
        self._entries = None  # R32UI texture of palette texels
        self._target = None  # RGBA32F gather texture
        self._fbo = None
        self._buffers: list[moderngl.Buffer] = []
        self._slots = [_Slot() for _ in range(RING)]
        self.capacity = 0
        self.last_count = 0
        self.ctx = ctx
        self.program = ctx.program(vertex_shader=load_shader("gather.vert.glsl"), fragment_shader=load_shader("gather.frag.glsl"))
        for name, unit in (("u_palette0", 0), ("u_palette1", 1), ("u_palette2", 2), ("u_entries", 3)):
            self.program[name] = unit
        self._vao = ctx.vertex_array(self.program, [])

    def _ensure(self, count: int) -> None:
        """Room for `count` entries; grows by powers of two so a changing crowd rarely reallocates."""
        if count <= self.capacity:
            return
        capacity = max(64, 1 << math.ceil(math.log2(count)))
        rows = math.ceil(capacity / ENTRIES_PER_ROW)
        width = min(capacity, ENTRIES_PER_ROW)
        for obj in (self._fbo, self._target, self._entries):
            if obj is not None:
                obj.release()
        self._entries = self.ctx.texture((width, rows), 1, dtype="u4")
        self._entries.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._target = self.ctx.texture((3 * width, rows), 4, dtype="f4")
        self._fbo = self.ctx.framebuffer(color_attachments=[self._target])
        # The frames queued in the ring survive the growth: each one's entries are copied into its new,
        # larger buffer on the GPU (ordered after the transfer that fills them), and its fence is
        # replaced by one after the copy. Capacity doubles, so a crowd that grows to 10,000 armed agents
        # does this about 8 times.
        for i, slot in enumerate(self._slots):
            grown = self.ctx.buffer(reserve=capacity * ENTRY_BYTES)
            if i < len(self._buffers):
                queued = slot.frame >= 0 and slot.agents is not None and slot.agents.size
                if queued:
                    self.ctx.copy_buffer(grown, self._buffers[i], size=int(slot.agents.size) * ENTRY_BYTES)
                    slot.fence.release()
                    slot.fence = Fence()
                else:
                    self._clear(slot)
                self._buffers[i].release()
                self._buffers[i] = grown
            else:
                self._buffers.append(grown)
                self._clear(slot)
        self.capacity = capacity

    @staticmethod
    def _clear(slot: _Slot) -> None:
        if slot.fence is not None:
            slot.fence.release()
        slot.frame, slot.agents, slot.joints, slot.fence = -1, None, None, None

    def gather(self, frame: int, processor, agents, joints, timer=None) -> bool:
        """Queue the gather and the transfer of this frame's (agent, joint) pairs. Returns False when
        there was nothing to gather (no pass ran). `processor` has just run for this frame."""
        agents = np.asarray(agents, np.int64).reshape(-1)
        joints = np.asarray(joints, np.int64).reshape(-1)
        if agents.shape != joints.shape:
            raise ReadbackError(f"gather needs one joint per agent, got {agents.size} agents and {joints.size} joints")
        if agents.size and (agents.min() < 0 or agents.max() >= processor.agents):
            raise ReadbackError(f"gather agents must be in [0, {processor.agents})")
        layout = processor.layout  # where each agent's character keeps its joints
        if joints.size:
            limit = np.array([p.joints for p in layout.parts], np.int64)[layout.part_of(agents)]
            if joints.min() < 0 or np.any(joints >= limit):
                raise ReadbackError(f"gather joints must be in [0, the agent's joint count); got joint {int(joints.max())} "
                                    f"for a character of {int(limit[np.argmax(joints >= limit)])} joints" if np.any(joints >= limit)
                                    else "gather joints must be >= 0")
        count = int(agents.size)
        self.last_count = count
        self._ensure(count)
        slot = self._slots[frame % RING]
        self._clear(slot)
        slot.frame, slot.agents, slot.joints = frame, agents, joints
        if count == 0:
            return False
        rows = math.ceil(count / ENTRIES_PER_ROW)
        width = min(count, ENTRIES_PER_ROW)
        texel_x, texel_y = layout.texel(agents, joints, processor.row_offset(0))
        packed = np.zeros(rows * width, np.uint32)
        packed[:count] = texel_code(texel_x, texel_y)
        self._entries.write(packed.tobytes(), viewport=(0, 0, width, rows))
        with timer.gpu("gather") if timer is not None else nullcontext():
            processor.bind_palette(0, self.program)
            self._entries.use(3)
            self._fbo.viewport = (0, 0, 3 * width, rows)
            self._fbo.use()
            self.ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND | moderngl.CULL_FACE)
            self._vao.render(moderngl.TRIANGLES, vertices=3)
        with timer.gpu("transfer") if timer is not None else nullcontext():
            # Into a pixel-pack buffer: glReadPixels returns at once and the copy runs on the GPU.
            self._fbo.read_into(self._buffers[frame % RING], viewport=(0, 0, 3 * width, rows), components=4, dtype="f4")
        slot.fence = Fence()
        return True

    def fetch(self, frame: int) -> SocketRead | None:
        """The read-back of `frame`, or None when that frame is not (or no longer) in the ring."""
        slot = self._slots[frame % RING]
        if slot.frame != frame or slot.agents is None:
            return None
        count = int(slot.agents.size)
        rows = np.empty((count, 3, 4), np.float32)
        wait_ms = copy_ms = 0.0
        stalled = False
        if count:
            t0 = time.perf_counter()
            stalled = not slot.fence.signaled()
            if stalled:
                slot.fence.wait()
            t1 = time.perf_counter()
            self._buffers[frame % RING].read_into(rows, size=count * ENTRY_BYTES)
            t2 = time.perf_counter()
            wait_ms, copy_ms = (t1 - t0) * 1e3, (t2 - t1) * 1e3
        return SocketRead(frame, slot.agents, slot.joints, rows, wait_ms, copy_ms, stalled)

    def reset(self) -> None:
        """Forget every queued frame (the palette they were gathered from is gone)."""
        for slot in self._slots:
            self._clear(slot)

    def gpu_bytes(self) -> int:
        return gpu_bytes([o for o in (self._entries, self._target, *self._buffers) if o is not None])

    def release(self) -> None:
        for slot in self._slots:
            self._clear(slot)
        for obj in (self._fbo, self._target, self._entries, *self._buffers, self._vao, self.program):
            if obj is not None:
                obj.release()
        self._fbo = self._target = self._entries = self._vao = self.program = None
        self._buffers = []
        self.capacity = 0
