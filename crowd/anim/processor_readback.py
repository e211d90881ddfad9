"""Synchronous read-backs of the processor's palette (skinning rows, morph pairs, impostor keys) and
of its foot-lock state: for tests and stats, never for a frame."""

from __future__ import annotations

import numpy as np

from .morph import MORPH_PAIRS


class ProcessorReadback:
    """AnimationProcessor's read-backs of the planes and buffers it owns."""

    def read_lock_state(self, character: int = 0) -> np.ndarray:
        """(N, legs, 4) float32 foot-lock state of one character's agents (synchronous: tests only): engaged
        legs (hold x, z, yaw, 1), free ones (the correction carried x, z, yaw, 0)."""
        part, block = self.parts[character], self.layout.parts[character]
        if part.lock_state is None:
            return np.zeros((0, 0 if part.legs is None else len(part.legs), 4), np.float32)
        return np.frombuffer(part.lock_state.read(), np.float32).reshape(block.count, len(part.legs), 4)

    def read_palette(self, age: int = 0) -> np.ndarray:
        """(N, J, 3, 4) float32 skinning matrix rows of the palette written `age` runs ago, read back
        synchronously (tests and stats only); J is the largest skeleton's, and a smaller character's
        agents have zeros past their own joints."""
        n = self.agents
        jmax = max(p.bake.joint_count for p in self.parts)
        if n == 0:
            return np.zeros((0, jmax, 3, 4), np.float32)
        first = self.row_offset(age) if self.runs else 0
        planes = self._read_planes()
        out = np.zeros((n, jmax, 3, 4), np.float32)
        for block in self.layout.parts:
            if not block.count:
                continue
            rows, k, jc, w = block.rows, block.agents_per_row, block.joints, block.width
            y0 = first + block.first_row
            for r, plane in enumerate(planes):
                out[block.first_agent:block.first_agent + block.count, :jc, r] = \
                    plane[y0:y0 + rows, :k * w].reshape(rows * k, w, 4)[:block.count, block.slots:]
        return out

    def read_morph_pairs(self, character: int = 0, age: int = 0) -> np.ndarray:
        """(N, MORPH_PAIRS, 2) float32 (target, weight) pairs of one character's agents, from the palette
        written `age` runs ago (synchronous: tests only); (N, 0, 2) for a character without morphs."""
        block = self.layout.parts[character]
        if not block.morph or not block.count:
            return np.zeros((block.count, 0, 2), np.float32)
        first = self.row_offset(age) if self.runs else 0
        rows, k, w = block.rows, block.agents_per_row, block.width
        y0 = first + block.first_row
        texels = [plane[y0:y0 + rows, :k * w].reshape(rows * k, w, 4)[:block.count, block.slots - 1] for plane in self._read_planes()]
        return np.concatenate(texels, axis=1).reshape(block.count, MORPH_PAIRS, 2)

    def read_impostor_keys(self, character: int = 0, age: int = 0) -> np.ndarray:
        """(N, 4) float32 impostor keys of one character's agents (clip, phase of the heaviest layer, 0, 0),
        from the palette written `age` runs ago (synchronous: tests only); (N, 0) without keys."""
        block = self.layout.parts[character]
        if not block.key or not block.count:
            return np.zeros((block.count, 0), np.float32)
        first = self.row_offset(age) if self.runs else 0
        rows, k, w = block.rows, block.agents_per_row, block.width
        y0 = first + block.first_row
        return self._read_planes()[0][y0:y0 + rows, :k * w].reshape(rows * k, w, 4)[:block.count, 0].copy()

    def _read_planes(self) -> list[np.ndarray]:
        """The three planes, every palette of the history, as (palette rows, width, 4) float32 (synchronous)."""
        return [np.frombuffer(p.read(), np.float32).reshape(p.layers * p.height, p.width, 4) for p in self.planes]

    def read_rows(self, agents: np.ndarray, joint, row_offsets: np.ndarray) -> np.ndarray:
        """(K, 3, 4) float32 skinning matrix rows of one joint (or one per agent) of some agents, each from
        the palette starting at its row offset (synchronous: tests and stats only)."""
        x, y = self.layout.texel(agents, joint, row_offsets)
        return np.stack([plane[y, x] for plane in self._read_planes()], axis=1)

    def nan_rows(self) -> int:
        """Agents whose palette row holds NaN or Inf (each character's own joints)."""
        pal = self.read_palette()
        if not len(pal):
            return 0
        bad = 0
        for block in self.layout.parts:
            rows = pal[block.first_agent:block.first_agent + block.count, :block.joints]
            bad += int(np.count_nonzero(~np.all(np.isfinite(rows), axis=(1, 2, 3))))
        return bad
