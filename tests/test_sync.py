"""PaletteSync: which palette each body is drawn with, so the weapon read back from frame F - N sits
in the hand of the body drawn with frame F - N's palette. Plain numpy, no GL."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crowd.draw.sync import PaletteSync


@dataclass
class Read:  # the fields of a SocketRead that PaletteSync looks at
    frame: int
    agents: np.ndarray
    joints: np.ndarray
    rows: np.ndarray


def ring(history: int):
    """The processor's row_offset(age) for a ring of `history` palettes, 10 rows each, after `runs` runs."""
    state = {"runs": 0}

    def row_offset(age: int) -> int:
        assert 0 <= age < min(history, max(state["runs"], 1))
        return ((state["runs"] - 1 - age) % history) * 10

    return state, row_offset


def read_of(frame: int, agents) -> Read:
    agents = np.asarray(agents, np.int64)
    return Read(frame, agents, np.zeros(len(agents), np.int64), np.zeros((len(agents), 3, 4), np.float32))


def test_bodies_use_the_palette_of_the_read_frame_once_it_is_kept():
    sync = PaletteSync(history=3, agents=4)
    state, row_offset = ring(3)
    for frame in range(5):
        state["runs"] += 1
        sync.processed(frame, fresh=frame == 0)
    # Frames 2, 3, 4 are kept (4 newest). A read of frame 2 is two palettes old.
    assert list(sync.frames) == [2, 3, 4] and sync.age(2) == 2 and sync.age(4) == 0 and sync.age(1) is None
    offsets = sync.row_offsets(2, row_offset)
    assert offsets.tolist() == [row_offset(2)] * 4
    assert sync.row_offsets(None, row_offset) == row_offset(0)
    assert sync.row_offsets(1, row_offset) == row_offset(0)  # frame 1's palette is gone: this frame's


def test_agents_born_after_the_read_frame_are_drawn_with_this_frame_and_get_no_weapon():
    sync = PaletteSync(history=3, agents=4)
    state, row_offset = ring(3)
    for frame in range(4):
        state["runs"] += 1
        sync.processed(frame, fresh=frame == 0)
    sync.spawned(np.array([False, True, False, False]), 3)  # agent 1 respawned in frame 3
    sync.resize(6, 3)  # agents 4 and 5 join in frame 3
    offsets = sync.row_offsets(1, row_offset)
    assert offsets.tolist() == [row_offset(2), row_offset(0), row_offset(2), row_offset(2), row_offset(0), row_offset(0)]
    kept = sync.synced(read_of(1, [0, 1, 2, 5, 7]), agents=6)  # 7 no longer exists
    assert kept.agents.tolist() == [0, 2] and kept.rows.shape == (2, 3, 4)
    assert sync.synced(None, 6) is None


def test_a_new_ring_forgets_every_kept_palette():
    sync = PaletteSync(history=2, agents=2)
    for frame in range(3):
        sync.processed(frame, fresh=False)
    assert list(sync.frames) == [1, 2]
    sync.reset(history=4)
    assert sync.history == 4 and not sync.frames and sync.synced(read_of(2, [0]), 2) is None
    sync.processed(5, fresh=False)
    sync.processed(6, fresh=True)  # a reallocated palette: frame 5's is gone too
    assert list(sync.frames) == [6]


def test_shrinking_keeps_the_birth_frames_of_the_agents_that_stay():
    sync = PaletteSync(history=2, agents=3)
    sync.spawned(np.array([2]), 9)
    sync.resize(2, 20)
    assert sync.born.tolist() == [0, 0]
    sync.resize(4, 20)
    assert sync.born.tolist() == [0, 0, 20, 20]
