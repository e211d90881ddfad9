"""Each frame's input to the processor: the agents' layers, validated, written where the processor reads
them (the compute path's buffer; the fragment path's texture, whole rows through its pixel-unpack buffer),
and the foot lock's motion and frame time."""

from __future__ import annotations

import math

import numpy as np

from ..frame import FrameError, validate_layers
from .processor_inputs import ProcessorError, check_motion


class LayerUpload:
    """AnimationProcessor's upload into the layers it reads and the foot-lock buffers it owns."""

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
        if self.path == "compute" and self.agents:
            buffer = self._layers_source = self._own_layers()
            buffer.orphan(buffer.size)  # fresh storage: the run still queued from the last frame reads its own
        first = 0
        for block in blocks:
            self._write_layers(block, first)
            first += len(block)

    def _own_layers(self):
        """The compute path's own layer buffer (zeros: weight 0, the rest pose), made at its first use."""
        if self._layer_buffer is None:
            self._layer_buffer = self.ctx.buffer(bytes(max(self.layer_bytes(), 16)))
            self._own["layers"].append(self._layer_buffer)
        return self._layer_buffer

    def read_layers(self) -> np.ndarray:
        """The (agents, LAYERS, 4) layers the next run reads (synchronous: tests)."""
        if self.path == "compute":
            source = self._layers_source if self._layers_source is not None else self._own_layers()
            data = np.frombuffer(source.read(size=self.agents * self.layer_count * 16), np.float32)
        else:
            data = np.frombuffer(self.layers_texture.read(), np.float32)
        return data[:self.agents * self.layer_count * 4].reshape(self.agents, self.layer_count, 4).copy()

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
        agent after agent, padded to whole texture rows, ``layer_bytes``): the compute path's next run reads
        it where it lies (it must live until then), the fragment path copies it into its texture on the
        GPU. The foot lock's motion is in its buffers already (``lock_motion_targets``), and `dt` is
        the frame's simulated seconds. Nothing is checked per agent: the GPU AI writes each character's
        clips from its own bake."""
        need = self.layer_bytes()
        if layers.size < need:
            raise ProcessorError(f"a layer buffer of {layers.size} bytes; {self.agents} agents need {need}")
        if self.legs is not None:
            if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt >= 0):
                raise ProcessorError(f"the foot lock needs a frame time >= 0 seconds, got {dt!r}")
            self._lock_dt = float(dt)
        if self.path == "compute":
            self._layers_source = layers  # read where it lies: no copy
        elif self.agents:
            self.layers_texture.write(layers, viewport=(0, 0, self.layer_agents_per_row * self.layer_count, self.layers_texture.height))

    def _write_layers(self, a: np.ndarray, first: int) -> None:
        """Layers of agents first .. first + len(a) - 1 into the layers texture: a partial first row, whole
        texture rows straight from the array (no padded copy), then a partial last row."""
        per_row, n = self.layer_agents_per_row, len(a)
        k = self.layer_count
        if self.path == "compute":
            if n:
                self._layer_buffer.write(np.ascontiguousarray(a), offset=first * k * 16)
            return
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
