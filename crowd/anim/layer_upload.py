"""Each frame's input to the processor: the agents' layers, validated, written into the layers texture
(whole rows through its pixel-unpack buffer), and the foot lock's motion and frame time."""

from __future__ import annotations

import math

import numpy as np

from ..frame import FrameError, validate_layers
from .processor_inputs import ProcessorError, check_motion


class LayerUpload:
    """AnimationProcessor's upload into the layers texture and the foot-lock buffers it owns."""

    def upload(self, layers, motion=None, dt: float = 0.0) -> None:
        """Validate and upload this frame's layers (N, L, 4), or a sequence of blocks of consecutive
        agents that together are N (the crowd's, then the player's: no copy to join them); N must equal
        the agent count, and each character's agents' clips and masks are its own bake's (a character's
        agents lie in one block). With the foot lock, also each agent's `motion` (N, 4): its ground step
        since the last run (x, z, metres, from float64 positions) and its front (x, z) times its scale,
        and the frame's simulated seconds `dt`."""
        blocks = [np.asarray(b) for b in layers] if isinstance(layers, (list, tuple)) else [np.asarray(layers)]
        if len(blocks) == 1 and len(self.parts) == 1:
            p = self.parts[0]
            blocks = [validate_layers(blocks[0], len(p.bake.clips), 0 if p.masks is None else p.masks.shape[0], self.layer_count)]
        else:
            if any(b.ndim != 3 for b in blocks):
                raise ProcessorError(f"layers must be (agents, {self.layer_count}, 4) arrays, got {[b.shape for b in blocks]}")
            blocks = [b if b.dtype == np.float32 and b.flags.c_contiguous else np.ascontiguousarray(b, np.float32) for b in blocks]
            starts = np.cumsum([0] + [len(b) for b in blocks])
            if starts[-1] != self.agents:
                raise ProcessorError(f"layers are for {int(starts[-1])} agents, the processor holds {self.agents}")
            for k, (p, part) in enumerate(zip(self.parts, self.layout.parts)):
                if not part.count:
                    continue
                b = int(np.searchsorted(starts, part.first_agent, side="right")) - 1
                if part.first_agent + part.count > starts[b + 1]:
                    raise ProcessorError(f"character {k}'s agents span two blocks of layers; a character's lie in one")
                rows = blocks[b][part.first_agent - starts[b]:part.first_agent - starts[b] + part.count]
                try:
                    validate_layers(rows, len(p.bake.clips), 0 if p.masks is None else p.masks.shape[0], self.layer_count)
                except FrameError as exc:
                    raise FrameError(f"character {k}: {exc}") from None
        if sum(len(b) for b in blocks) != self.agents:
            raise ProcessorError(f"layers are for {sum(len(b) for b in blocks)} agents, the processor holds {self.agents}")
        if self.legs is not None:
            m = check_motion(motion, self.agents)
            if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt >= 0):
                raise ProcessorError(f"the foot lock needs a frame time >= 0 seconds, got {dt!r}")
            self._lock_dt = float(dt)
            for p, block in zip(self.parts, self.layout.parts):
                if p.lock_motion is not None and block.count:
                    # A fresh store for each frame's motion: the runs still queued read the last one.
                    part_motion = m[block.first_agent:block.first_agent + block.count]
                    p.lock_motion.orphan(part_motion.nbytes)
                    p.lock_motion.write(part_motion)
        first = 0
        for block in blocks:
            self._write_layers(block, first)
            first += len(block)

    def layer_bytes(self) -> int:
        """Bytes of the layers of every agent row padded to whole rows of the layers texture: the size of a
        GPU buffer ``upload_from`` copies from."""
        rows = math.ceil(self.agents / self.layer_agents_per_row)
        return rows * self.layer_agents_per_row * self.layer_count * 16

    def lock_motion_targets(self) -> list:
        """(first agent, agents, buffer) of each character whose feet the lock holds: where a crowd on the
        GPU writes its foot-lock motion (``upload``'s `motion`, the same (agents, 4) float32 rows)."""
        if self.legs is None:
            return []
        return [(block.first_agent, block.count, p.lock_motion) for p, block in zip(self.parts, self.layout.parts)
                if p.lock_motion is not None and block.count]

    def upload_from(self, layers, dt: float = 0.0) -> None:
        """This frame's layers from a GPU buffer the GPU wrote (a crowd on the GPU: crowd.frame's layers,
        agent after agent, padded to whole texture rows, ``layer_bytes``), copied into the layers texture
        on the GPU; the foot lock's motion is in its buffers already (``lock_motion_targets``), and `dt` is
        the frame's simulated seconds. Nothing is checked per agent: the GPU AI writes each character's
        clips from its own bake."""
        need = self.layer_bytes()
        if layers.size < need:
            raise ProcessorError(f"a layer buffer of {layers.size} bytes; {self.agents} agents need {need}")
        if self.legs is not None:
            if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt >= 0):
                raise ProcessorError(f"the foot lock needs a frame time >= 0 seconds, got {dt!r}")
            self._lock_dt = float(dt)
        if self.agents:
            self.layers_texture.write(layers, viewport=(0, 0, self.layer_agents_per_row * self.layer_count, self.layers_texture.height))

    def _write_layers(self, a: np.ndarray, first: int) -> None:
        """Layers of agents first .. first + len(a) - 1 into the layers texture: a partial first row, whole
        texture rows straight from the array (no padded copy), then a partial last row."""
        per_row, n = self.layer_agents_per_row, len(a)
        k = self.layer_count
        done = 0
        head = min((-first) % per_row, n)
        if head:
            row, x = divmod(first, per_row)
            self.layers_texture.write(np.ascontiguousarray(a[:head]), viewport=(x * k, row, head * k, 1))
            done = head
        full = (n - done) // per_row
        if full:
            rows = a[done:done + full * per_row]
            unpack = self._layer_unpack
            unpack.orphan(unpack.size)  # fresh storage: the copy still queued from the last frame keeps its own
            unpack.write(rows)
            self.layers_texture.write(unpack, viewport=(0, (first + done) // per_row, per_row * k, full))
            done += full * per_row
        if done < n:
            self.layers_texture.write(np.ascontiguousarray(a[done:]), viewport=(0, (first + done) // per_row, (n - done) * k, 1))
