"""Which agents each draw instances: the lists every cull path fills and every pass draws from.

Draws of pieces worn by the same agents at the same LOD read one list: a character's pieces every agent
wears share the (character, LOD) list, and the pieces of one choice of a variation group share the
(character, LOD, group, choice) list. So a character of 200 unmergeable pieces costs its agents one entry
per LOD side in a pass, not 200, and nothing here bounds the pieces, groups, choices or LODs a character has.

A list entry is 4 bytes: the agent's index in the low ENTRY_AGENT_BITS bits and the fade code of this copy
in the top byte (shaders/lod_fade.glsl: 255 for none; an agent within the fade band of a LOD switch is
listed at both LODs). The draws read the agent's 32-byte record (``RECORD_DTYPE``) from the crowd's one
record buffer through a buffer texture (shaders/agent_instance.glsl), so a pass's lists cost 4 bytes an
entry and the records are written once.

The record: position_scale (camera-relative origin, uniform scale); fields x: the palette texel code of
its joint 0, y: tint RGB with the agent's character in the top byte, z: cos and sin of its heading as
snorm16, w: its variation choices, each group's in ``ListPlan.choice_bits`` bits from its shift.

Morph routing (the compute cull only): a list of a character whose pieces have plain twins has two
parts, the agents whose morph weights move a target (MOVING) and the rest (STILL), one after the other,
so a piece without morphs draws both parts as one range (ALL), a morph draw the first, its plain twin
the second.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from ..errors import CrowdError

RECORD_DTYPE = np.dtype([("position_scale", "<f4", 4), ("packed", "<u4", 4)])
ENTRY_AGENT_BITS = 24
MAX_AGENTS = 1 << ENTRY_AGENT_BITS  # agents a list entry can name
NO_FADE = 255  # the fade code of an entry that is not in a fade band
CHARACTER_SHIFT = 24  # where fields.y keeps the agent's character (the tint's RGB below it)
MAX_CHARACTERS = 1 << (32 - CHARACTER_SHIFT)
CHOICE_BITS = 32  # fields.w: every group's choice
ALL, MOVING, STILL = 0, 1, 2  # the part of its list a draw reads


class ListError(CrowdError, ValueError):
    """A cast whose lists cannot be laid out; the message is one line."""


class ListKey(NamedTuple):
    """The agents of `character` drawn at `lod` (its impostor: its mesh LOD count) whose choice in variation
    group `group` (an index into ``ListPlan.group_names``; -1 for the pieces every agent wears) is `choice`."""

    character: int
    lod: int
    group: int = -1
    choice: int = 0


class DrawSpec(NamedTuple):
    """What the lists need of one (piece, LOD) draw."""

    character: int
    lod: int
    group: int  # index into the cast's group names, -1: a piece every agent wears
    choice: int  # its index among its group's pieces (0 for a common piece)
    part: int = ALL  # ALL, or MOVING / STILL for a morph draw and its plain twin (the compute cull)


@dataclass(frozen=True)
class ListPlan:
    """The lists of a cast and where each draw finds its instances, shared by the three cull paths."""

    keys: tuple[ListKey, ...]
    draw_list: np.ndarray  # int64 (draws,): each draw's list
    draw_part: np.ndarray  # int64 (draws,): ALL, MOVING or STILL
    lod_slots: tuple[int, ...]  # per character: the LODs its agents can be at (mesh LODs, then its impostor)
    mesh_lods: tuple[int, ...]  # per character: its mesh LODs
    choices: np.ndarray  # int64 (characters, groups): a character's pieces in each group (0: not in it)
    choice_shift: tuple[int, ...]  # per group: where fields.w keeps its choice
    choice_bits: tuple[int, ...]  # per group: how many bits

    @staticmethod
    def build(draws: list[DrawSpec], group_choices: list[list[int]], mesh_lods: list[int], impostor: list[bool]) -> "ListPlan":
        """`group_choices[c][g]`: character c's choices in group g (0 where it has none; a group's choice 0
        may have no piece, such as the impostor's empty hand). `mesh_lods[c]`: its mesh LODs;
        `impostor[c]`: whether its agents become impostors past the impostor distance (LOD mesh_lods[c])."""
        characters = len(mesh_lods)
        if not 1 <= characters <= MAX_CHARACTERS:
            raise ListError(f"a crowd draws 1 to {MAX_CHARACTERS} characters (a byte of each agent's record), got {characters}")
        choices = np.array(group_choices, np.int64).reshape(characters, -1)
        widest = choices.max(axis=0) if choices.size else np.zeros(0, np.int64)
        bits = [int(max(n - 1, 0)).bit_length() for n in widest]
        if sum(bits) > CHOICE_BITS:
            raise ListError(f"the cast's {len(bits)} variation groups need {sum(bits)} bits of choices an agent, more than the "
                            f"{CHOICE_BITS} of its record: give fewer groups their own pieces")
        shift = np.concatenate([[0], np.cumsum(bits)[:-1]]).astype(int).tolist() if bits else []
        keys = list(dict.fromkeys(ListKey(d.character, d.lod, d.group, d.choice if d.group >= 0 else 0) for d in draws))
        index = {k: i for i, k in enumerate(keys)}
        draw_list = np.array([index[ListKey(d.character, d.lod, d.group, d.choice if d.group >= 0 else 0)] for d in draws], np.int64)
        for d in draws:
            if d.group >= 0 and not 0 <= d.choice < choices[d.character, d.group]:
                raise ListError(f"a draw of character {d.character} is choice {d.choice} of group {d.group}, which has {choices[d.character, d.group]}")
        slots = tuple(int(n) + int(i) for n, i in zip(mesh_lods, impostor))
        return ListPlan(tuple(keys), draw_list, np.array([d.part for d in draws], np.int64), slots, tuple(int(n) for n in mesh_lods),
                        choices, tuple(shift), tuple(bits))

    @property
    def groups(self) -> int:
        return int(self.choices.shape[1])

    def columns(self, character: int) -> int:
        """Columns of a character's list table: its common pieces, then every choice of every group it has."""
        return 1 + int(self.choices[character].sum())

    def group_columns(self, character: int) -> np.ndarray:
        """int64 (groups,): the column of choice 0 of each group in the character's table (-1: not in it)."""
        n = self.choices[character]
        first = 1 + np.concatenate([[0], np.cumsum(n)[:-1]]) if len(n) else np.zeros(0, np.int64)
        return np.where(n > 0, first, -1).astype(np.int64)

    def table(self, character: int) -> np.ndarray:
        """int64 (lod slots, columns): the list of the character's agents at a LOD in a column, -1 where no
        piece is drawn (its column 0 where it has no common piece at that LOD)."""
        out = np.full((self.lod_slots[character], self.columns(character)), -1, np.int64)
        first = self.group_columns(character)
        for i, key in enumerate(self.keys):
            if key.character == character:
                out[key.lod, 0 if key.group < 0 else first[key.group] + key.choice] = i
        return out

    def per_agent(self, character: int) -> int:
        """The most entries one of its agents has on one side of a LOD switch: its common pieces and one
        piece per group it has."""
        return 1 + int(np.count_nonzero(self.choices[character]))

    def stats_first(self) -> np.ndarray:
        """int64 (characters + 1,): where each character's agents-per-LOD counters start, one per LOD slot."""
        return np.concatenate([[0], np.cumsum(self.lod_slots)]).astype(np.int64)

    def pack_choices(self, variants: list[np.ndarray | None], lo: int, hi: int, out: np.ndarray) -> None:
        """Agents lo..hi's choices (per group, an index array over every agent or None for all 0) into
        their records' fields.w `out` (uint32 (hi - lo,))."""
        out[:] = 0
        for g, v in enumerate(variants):
            if v is not None and self.choice_bits[g]:
                out |= v[lo:hi].astype(np.uint32) << np.uint32(self.choice_shift[g])


def entries(agents: np.ndarray, codes: np.ndarray | int = NO_FADE) -> np.ndarray:
    """uint32 list entries of `agents` with fade `codes`."""
    return np.asarray(agents, np.uint32) | (np.asarray(codes, np.uint32) << np.uint32(ENTRY_AGENT_BITS))


def entry_agents(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(agents, fade codes) of uint32 list entries."""
    v = np.asarray(values, np.uint32)
    return (v & np.uint32(MAX_AGENTS - 1)).astype(np.int64), (v >> np.uint32(ENTRY_AGENT_BITS)).astype(np.int64)
