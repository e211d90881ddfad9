"""The game's few facts from a crowd on the GPU, read back without a stall: a frame's counters (the blows
on the player, respawns, kills and hurts so far, the agents in each state, the nearest agents two searches
found) are copied into a ring of small buffers behind a fence, and the CPU reads the copy of frame F - N
once the GPU has finished it, as the weapons' socket read-back does. The running totals only grow, so
a copy the CPU never reads loses nothing: the next one's totals include it."""

from __future__ import annotations

import moderngl
import numpy as np

from ...gl import FencedSlots, GLObjects, GLStage
from ..config import STATE_NAMES

RING = 3
NONE = 0xFFFFFFFF


def facts_of(data: bytes) -> dict:
    """The counters' words (shaders/sim/agents.glsl, Counters) as a dict."""
    words = np.frombuffer(data, np.uint32)
    at = words[16:18].view(np.float32)
    row = None
    if words[19] != NONE:  # (-1: no selected agent)
        motion, heading, codes = words[20:24].view(np.float32), words[24:28].view(np.float32), words[28:32].view(np.int32)
        row = {"agent": int(words[19]), "x": float(motion[0]), "z": float(motion[1]), "vx": float(motion[2]), "vz": float(motion[3]),
               "phase": float(heading[2]), "scale": float(heading[3]), "state": int(codes[0]), "action": int(codes[1]),
               "health": int(codes[2])}
    return {"near": int(words[18]), "selected": row, "blows": int(words[0]), "respawns": int(words[1]), "kills": int(words[2]), "hurt": int(words[3]),
            "states": {name: int(words[4 + code]) for code, name in enumerate(STATE_NAMES)},
            "struck": int(words[14]) if words[14] != NONE else -1, "nearest": int(words[15]) if words[15] != NONE else -1,
            "nearest_at": (float(at[0]), float(at[1])),
            "picked": (int(words[34]), int(words[33]) if words[33] != NONE else -1)}  # (the request it answers, its agent)


class FactRing(GLStage):
    """RING copies of the counters, each with the frame it holds and its fence."""

    def __init__(self, ctx: moderngl.Context, size: int):
        self.ctx = ctx
        self._objects = GLObjects()
        self._slots = [self._objects.add(ctx.buffer(reserve=size, dynamic=True)) for _ in range(RING)]  # (where the CPU reads without waiting)
        self._done = FencedSlots(RING)
        self.read_bytes = 0  # bytes read back by the last fetch

    def capture(self, frame: int, counters: moderngl.Buffer) -> None:
        """Copy the counters as frame `frame` left them into its slot, behind a fence."""
        self.ctx.copy_buffer(self._slots[frame % RING], counters)
        self._done.mark(frame)

    def forget(self) -> None:
        """The copies queued so far are of a crowd that is gone (a new one was loaded): none is read."""
        self._done.forget()

    def fetch(self, frame: int) -> dict | None:
        """Frame `frame`'s facts if its copy is done (never waits), else None."""
        self.read_bytes = 0
        if not self._done.ready(frame):
            return None
        data = self._slots[frame % RING].read()
        self.read_bytes = len(data)
        facts = facts_of(data)
        facts["frame"] = frame
        return facts

    def release(self) -> None:
        self._done.release()
        self._objects.release()
