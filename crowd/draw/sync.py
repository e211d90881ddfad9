"""Which palette each body is drawn with, so that a weapon placed from the read-back of frame F - N sits
in the hand of a body drawn with the palette of frame F - N.

The processor keeps a ring of the last palettes (``AnimationProcessor.row_offset(age)`` says where the
palette of ``age`` frames ago starts). ``PaletteSync`` remembers which frame each kept palette came
from and in which frame each agent (re)spawned, and from those answers two questions per frame:
- ``row_offsets``: the first palette row each agent is drawn from. Agents that existed in the frame
  the read-back came from are drawn from that frame's palette; the rest (and everyone, when that
  palette is gone) from this frame's.
- ``synced``: the part of a read-back whose bodies are drawn from its own frame's palette. A weapon is
  placed only for those, so no weapon is ever drawn against another frame's hand.

No GL: the pipeline feeds it frame numbers and the processor's row offsets.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from typing import Callable

import numpy as np

from ..frame import move_agents


class PaletteSync:
    def __init__(self, history: int, agents: int = 0):
        self.frames: deque[int] = deque(maxlen=history)  # the frame of each kept palette, oldest first
        self.born = np.zeros(agents, np.int64)  # the frame in which each agent (re)spawned

    @property
    def history(self) -> int:
        return self.frames.maxlen

    def reset(self, history: int | None = None) -> None:
        """A new palette ring (another history, or a new bake): the palettes kept so far are gone."""
        self.frames = deque(maxlen=self.history if history is None else history)

    def resize(self, agents: int, frame: int, moves=None) -> None:
        """Agents kept keep their birth frame; new ones are born in `frame`. `moves`: where each character's
        kept agents went (crowd.frame.cast_moves; None: agents 0 .. min(old, new) - 1 stay where they are)."""
        moves = [(0, 0, min(agents, len(self.born)))] if moves is None else moves
        self.born = move_agents(self.born, moves, agents, fill=frame)

    def spawned(self, agents, frame: int) -> None:
        """Agents (indices or a mask) that (re)spawned in `frame`."""
        self.born[agents] = frame

    def processed(self, frame: int, fresh: bool) -> None:
        """The processor wrote `frame`'s palette; `fresh`: into a newly allocated ring (nothing older is kept)."""
        if fresh:
            self.frames.clear()
        self.frames.append(frame)

    def age(self, frame: int) -> int | None:
        """How many palettes ago `frame`'s palette was written, or None when it is no longer kept."""
        if frame not in self.frames:
            return None
        return len(self.frames) - 1 - list(self.frames).index(frame)

    def row_offsets(self, read_frame: int | None, row_offset: Callable[[int], int]) -> int | np.ndarray:
        """First palette row per agent (or one int for all): frame `read_frame`'s palette for the agents
        that existed then, this frame's for the others. `row_offset(age)` is the processor's."""
        latest = row_offset(0)
        age = None if read_frame is None else self.age(read_frame)
        if age is None:
            return latest
        return np.where(self.born <= read_frame, row_offset(age), latest).astype(np.uint32)

    def synced(self, read, agents: int, born_limit: int | None = None):
        """`read` (a SocketRead) limited to agents still present whose body is drawn with the palette of
        its frame; None when there is no read or that palette is gone. A crowd on the GPU says when its
        entries were born itself (`read.born`, spawn steps; `born_limit` the step count its frame had)."""
        if read is None or read.frame not in self.frames:
            return None
        keep = read.agents < agents
        if born_limit is not None:
            keep &= read.born <= born_limit
        else:
            keep[keep] = self.born[read.agents[keep]] <= read.frame
        if keep.all():  # the usual frame: nobody (re)spawned since the read, and no copy of its rows
            return read
        return dataclasses.replace(read, agents=read.agents[keep], joints=read.joints[keep], rows=read.rows[keep])
