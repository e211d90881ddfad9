"""The palette's layout: where each agent's skinning matrices live in a ring slot of the planes
(PaletteLayout, a PalettePart per character), the texel codes readers address them by, and the
driver's limits a palette layer is cut to. The processor writes by it; the draws and read-backs read by it."""

from __future__ import annotations

import math
from dataclasses import dataclass

import moderngl
import numpy as np

# Agents side by side in one palette texture row: keeps textures under 4096 texels wide, a size every
# GL 3.3+ driver we target accepts (GL_MAX_TEXTURE_SIZE is 16384 on llvmpipe, 32768 on NVIDIA).
MAX_TEXTURE_WIDTH = 1 << 12

TEXEL_ROW_SHIFT = 12  # a texel code is x | y << 12: x < MAX_TEXTURE_WIDTH = 2^12, y < 2^20 palette rows
MAX_PALETTE_ROWS = 1 << (32 - TEXEL_ROW_SHIFT)


def palette_texel(agents, joints, row_offset, agents_per_row: int, joint_count: int) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) int64 texel of joint(s) `joints` of `agents` in a palette plane, in the ring slot that
    starts at row `row_offset` (an int, or one per agent); y counts rows across layers. The one
    statement of the palette layout."""
    agents = np.asarray(agents, np.int64)
    return (agents % agents_per_row) * joint_count + np.asarray(joints, np.int64), agents // agents_per_row + np.asarray(row_offset, np.int64)


def palette_limits(ctx: moderngl.Context) -> tuple[int, int]:
    """(texture rows a palette layer may have, layers an array texture may have) on this context."""
    return int(ctx.info.get("GL_MAX_TEXTURE_SIZE", 16384)), int(ctx.info.get("GL_MAX_ARRAY_TEXTURE_LAYERS", 256))


def texel_code(x, y) -> np.ndarray:
    """uint32 code of palette texels (x, y), as shaders/palette.glsl reads it."""
    return np.asarray(x, np.uint32) | (np.asarray(y, np.uint32) << np.uint32(TEXEL_ROW_SHIFT))


@dataclass(frozen=True)
class PalettePart:
    """One character's block of a palette ring slot: its agents (first_agent .. first_agent + count - 1),
    agents_per_row of them side by side in a texture row, each `width` texels wide (`slots` texels before
    its `joints`: its impostor key where impostors are drawn (crowd.draw.impostors), then its morph pairs
    where `morph` (crowd.anim.morph)), from row first_row."""

    first_agent: int
    count: int
    joints: int
    agents_per_row: int
    first_row: int
    slots: int = 0
    morph: bool = False  # the texel before joint 0 holds the agent's morph pairs

    @property
    def key(self) -> bool:
        """Whether the agent's first texel holds its impostor key (the clip and phase its impostor shows)."""
        return self.slots > int(self.morph)

    @property
    def rows(self) -> int:
        return math.ceil(self.count / self.agents_per_row)

    @property
    def width(self) -> int:
        return self.slots + self.joints


@dataclass(frozen=True)
class PaletteLayout:
    """Where each agent's skinning matrices live in a palette ring slot: every character of the cast has
    a block of rows of its own, laid out for its own joint count (no texel spent on a larger skeleton's
    joints), one after the other in the cast's order. The one statement of the layout: the processor
    writes by it, the instance records and the read-back address by it (``texel``)."""

    parts: tuple[PalettePart, ...]

    @staticmethod
    def make(joint_counts, counts, slots=None, morphs=None) -> "PaletteLayout":
        """`slots`: each character's texels before an agent's joints (None: none); `morphs`: whether the
        last of them holds morph pairs (None: wherever there is a slot)."""
        parts, agent, row = [], 0, 0
        slots = slots or [0] * len(joint_counts)
        morphs = morphs if morphs is not None else [s > 0 for s in slots]
        for joints, count, s, m in zip(joint_counts, counts, slots, morphs):
            part = PalettePart(agent, int(count), int(joints), max(1, MAX_TEXTURE_WIDTH // (int(joints) + int(s))), row, int(s), bool(m))
            parts.append(part)
            agent += part.count
            row += part.rows
        return PaletteLayout(tuple(parts))

    @property
    def agents(self) -> int:
        return sum(p.count for p in self.parts)

    @property
    def rows(self) -> int:
        """Palette rows one ring slot holds."""
        return sum(p.rows for p in self.parts)

    @property
    def width(self) -> int:
        """Texels a palette row has: the widest character's (constant for a cast, whatever its counts)."""
        return max(p.agents_per_row * p.width for p in self.parts)

    @property
    def counts(self) -> tuple[int, ...]:
        return tuple(p.count for p in self.parts)

    def part_of(self, agents) -> np.ndarray:
        """Index of the part (character) of each of `agents`."""
        firsts = np.array([p.first_agent + p.count for p in self.parts[:-1]], np.int64)
        return np.searchsorted(firsts, np.asarray(agents, np.int64), side="right")

    def texel(self, agents, joints, row_offset=0) -> tuple[np.ndarray, np.ndarray]:
        """(x, y) int64 palette texel of joint(s) `joints` of `agents` (global numbers) in the ring slot
        that starts at row `row_offset` (an int, or one per agent); y counts rows across layers."""
        agents = np.asarray(agents, np.int64)
        if len(self.parts) == 1:
            p = self.parts[0]
            x, y = palette_texel(agents, np.asarray(joints, np.int64) + p.slots, row_offset, p.agents_per_row, p.width)
            return x, y + p.first_row
        k = self.part_of(agents)
        table = np.array([(p.first_agent, p.agents_per_row, p.width, p.first_row, p.slots) for p in self.parts], np.int64)
        first, per_row, width, first_row, slots = (table[k, c] for c in range(5))
        local = agents - first
        return ((local % per_row) * width + slots + np.asarray(joints, np.int64),
                first_row + local // per_row + np.asarray(row_offset, np.int64))

    def agents_at(self, x, y) -> np.ndarray:
        """The agents whose joints' texels (x, y) are, y counted from their ring slot's first row: the
        inverse of ``texel`` (tests and benchmarks read the lists back by it)."""
        x, y = np.asarray(x, np.int64), np.asarray(y, np.int64)
        table = np.array([(p.first_agent, p.agents_per_row, p.width, p.first_row) for p in self.parts], np.int64)
        k = np.searchsorted(table[:, 3], y, side="right") - 1
        return table[k, 0] + (y - table[k, 3]) * table[k, 1] + x // table[k, 2]
