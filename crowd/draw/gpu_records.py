"""Every agent's record packed on the GPU from the GPU AI's state (shaders/records.comp.glsl), the twin
of crowd.draw.records.RecordPacker for a crowd that lives on the GPU: nothing per agent crosses from the
CPU but the survivor's one row."""

from __future__ import annotations

import moderngl
import numpy as np

from ..anim.palette_layout import PaletteLayout, texel_code
from ..frame import SimFrame
from ..gl import GLObjects, GLStage, has_uniform, load_shader, set_uniforms
from ..sim.gpu.state import FIELDS
from .cull_lists import CHARACTER_SHIFT, RECORD_DTYPE, ListPlan
from .impostors import HELD_GROUP
from .packing import rgba8, write_heading

GROUP = 256
TEXEL_BASE, RECORDS = 17, 18
SHADER_STORAGE = 0x2000
_READS = ("motion", "heading", "codes", "looks")


class GpuRecordPass(GLStage):
    """The record pass and its table of each agent's palette texel (remade when the layout changes)."""

    def __init__(self, ctx: moderngl.Context, plan: ListPlan, group_names: list[str], weapon_first: list[int]):
        self.ctx = ctx
        self._objects = GLObjects()
        self.plan, self.group_names = plan, list(group_names)
        self._weapon_first = [int(w) for w in weapon_first] or [0]
        self.program = self._objects.add(ctx.compute_shader(load_shader("records.comp.glsl", {"KINDS": len(self._weapon_first)})))
        self._layout: PaletteLayout | None = None
        self._texel_base = None
        self.sent_bytes = 0  # what the frame wrote from the CPU (the caller zeroes it when a frame starts)

    def _shift(self, group: str) -> int:
        if group not in self.group_names:
            return -1
        g = self.group_names.index(group)
        return int(self.plan.choice_shift[g]) if self.plan.choice_bits[g] else -1

    def texel_base(self, palette: PaletteLayout, agents: int) -> moderngl.Buffer:
        """Each crowd agent's palette texel of joint 0 in a ring slot starting at row 0 (joint j's is j
        more: an agent's joints lie side by side in a row), made anew when the layout changes."""
        if self._layout != palette or self._texel_base is None:
            self._layout = palette
            x, y = palette.texel(np.arange(max(agents, 1)), 0, 0)
            if self._texel_base is not None:
                self._objects.remove(self._texel_base)
                self._texel_base.release()
            self._texel_base = self._objects.add(self.ctx.buffer(texel_code(x, y).astype(np.uint32).tobytes()))
            self.sent_bytes += self._texel_base.size
        return self._texel_base

    def run(self, frame: SimFrame, records, eye: np.ndarray, palette: PaletteLayout, row_offset: int, latest_offset: int,
            born_limit: int) -> None:
        """Pack `frame`'s rows into `records` (crowd.draw.records.AgentRecords, sized here). `eye`: float64
        world; `row_offset` the ring slot most bodies are drawn from, `latest_offset` this frame's, for
        agents whose spawned_step is above `born_limit` (-1: everyone from `row_offset`)."""
        n, rows = frame.agents, frame.rows
        records.reserve(rows)
        self.texel_base(palette, n)
        if n:
            for name in _READS:
                frame.buffers[name].bind_to_storage_buffer(FIELDS[name][0])
            self._texel_base.bind_to_storage_buffer(TEXEL_BASE)
            records.buffer.bind_to_storage_buffer(RECORDS)
            p = self.program
            rel = np.asarray(eye, np.float64) - np.array([frame.origin[0], 0.0, frame.origin[1]])
            values = {"u_n": n, "u_eye": tuple(float(v) for v in rel), "u_row_code": int(texel_code(0, row_offset)),
                      "u_latest_code": int(texel_code(0, latest_offset)), "u_born_limit": int(born_limit),
                      "u_head_shift": self._shift("head"), "u_held_shift": self._shift(HELD_GROUP)}
            set_uniforms(p, **values)
            if has_uniform(p, "u_weapon_first"):
                p["u_weapon_first"].write(np.array(self._weapon_first, np.int32).tobytes())
            p.run((n + GROUP - 1) // GROUP)
            self.ctx.memory_barrier(SHADER_STORAGE | 0x8)  # (and texel fetches: the draws read records through a buffer texture)
        if frame.extra is not None:
            row = self._extra_rows(frame, eye, palette, latest_offset)
            records.buffer.write(row.tobytes(), offset=n * RECORD_DTYPE.itemsize)
            self.sent_bytes += row.nbytes

    def _extra_rows(self, frame: SimFrame, eye: np.ndarray, palette: PaletteLayout, row_offset: int) -> np.ndarray:
        """The survivor's record(s), packed on the CPU as RecordPacker packs any row."""
        extra, n = frame.extra, frame.agents
        count = len(extra)
        out = np.zeros(count, RECORD_DTYPE)
        out["position_scale"][:, :3] = extra.position - np.asarray(eye, np.float64)
        out["position_scale"][:, 3] = extra.scale
        x, y = palette.texel(np.arange(n, n + count), 0, row_offset)
        fields = out["packed"]
        fields[:, 0] = texel_code(x, y)
        kinds = np.full(count, len(frame.cast), np.uint32)
        fields[:, 1] = (rgba8(extra.tint) & np.uint32((1 << CHARACTER_SHIFT) - 1)) | (kinds << np.uint32(CHARACTER_SHIFT))
        heading = np.zeros(count, np.uint32)
        write_heading(extra.yaw, heading)
        fields[:, 2] = heading
        return out

    def release(self) -> None:
        self._objects.release()
        self._texel_base = None
