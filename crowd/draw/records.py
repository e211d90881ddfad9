"""Every agent's 32-byte record, packed once a frame and held in one GPU buffer that every cull path and
every pass reads.

The record (crowd.draw.cull_lists has the field layout) is what a skinned draw needs of its agent: where it
stands relative to the camera, its palette row, tint and heading; the culls add its character and
variation choices. The lists hold 4-byte entries naming agents, and the vertex shaders fetch the record
through a buffer texture over this buffer (shaders/agent_instance.glsl): GL 3.1 core, so the GL 3.3 and
macOS 4.1 paths read it the same way as the compute path.
"""

from __future__ import annotations

import ctypes

import moderngl
import numpy as np

from ..errors import CrowdError
from ..anim.palette_layout import PaletteLayout, texel_code
from ..frame import Instances
from ..gl import GLStage, current_context_function
from ..spans import over_spans
from .cull_lists import CHARACTER_SHIFT, MAX_AGENTS, RECORD_DTYPE, ListPlan
from .packing import rgba8, write_heading

RECORDS_UNIT = 12  # the texture unit of the records' buffer texture (0-2 palette, 3 shadows, 4-5 morphs, 6 and 11 albedo, 7 pyramid, 8-10 impostors)
_GL_TEXTURE_BUFFER, _GL_RGBA32UI, _GL_TEXTURE0 = 0x8C2A, 0x8D70, 0x84C0
_api: dict | None = None


def _gl() -> dict:
    """Buffer textures, which moderngl has no object for (GL 3.1 core)."""
    global _api
    if _api is None:
        void, uint, int_ = None, ctypes.c_uint, ctypes.c_int
        uints = ctypes.POINTER(ctypes.c_uint)
        types = {"glGenTextures": (void, int_, uints), "glDeleteTextures": (void, int_, uints), "glBindTexture": (void, uint, uint),
                 "glActiveTexture": (void, uint), "glTexBuffer": (void, uint, uint, uint), "glUseProgram": (void, uint),
                 "glGetUniformLocation": (int_, uint, ctypes.c_char_p), "glUniform1i": (void, int_, int_)}
        _api = {name: current_context_function(name, ctypes.CFUNCTYPE(*sig)) for name, sig in types.items()}
    return _api


def use_records_unit(program: moderngl.Program, name: str = "u_agents") -> None:
    """Point `program`'s usamplerBuffer `name` at RECORDS_UNIT (moderngl's uniform setter does not know
    buffer samplers, and writes them nothing)."""
    gl = _gl()
    location = gl["glGetUniformLocation"](program.glo, name.encode())
    if location >= 0:
        gl["glUseProgram"](program.glo)  # (moderngl binds its program on each draw: nothing of its to restore)
        gl["glUniform1i"](location, RECORDS_UNIT)
        gl["glUseProgram"](0)


class RecordError(CrowdError, ValueError):
    """Records this GPU cannot hold; the message is one line."""


class AgentRecords(GLStage):
    """The records' buffer (made once, re-sized in place so vertex arrays built on it stay valid) and the
    buffer texture the draws read it through."""

    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self._texture = None
        self.buffer = ctx.buffer(reserve=RECORD_DTYPE.itemsize)
        # Two RGBA32UI texels a record; a driver may offer fewer than a million agents need.
        self.max_texels = int(ctx.info.get("GL_MAX_TEXTURE_BUFFER_SIZE", 1 << 27))
        names = (ctypes.c_uint * 1)()
        _gl()["glGenTextures"](1, names)
        self._texture = names
        self.agents = 0
        self._attach()

    def _attach(self) -> None:
        gl = _gl()
        gl["glActiveTexture"](_GL_TEXTURE0 + RECORDS_UNIT)
        gl["glBindTexture"](_GL_TEXTURE_BUFFER, self._texture[0])
        gl["glTexBuffer"](_GL_TEXTURE_BUFFER, _GL_RGBA32UI, self.buffer.glo)  # (again after a re-size: a new data store)

    def write(self, records: np.ndarray) -> None:
        """This frame's records, in one write (the array itself: no copy)."""
        self.reserve(len(records))
        if len(records):
            self.buffer.write(records)

    def reserve(self, n: int) -> None:
        """A buffer of `n` records (the GPU writes them: crowd.draw.gpu_records), or RecordError."""
        if n > MAX_AGENTS:
            raise RecordError(f"{n:,} agents, more than the {MAX_AGENTS:,} a list entry can name")
        if 2 * n > self.max_texels:
            raise RecordError(f"{n:,} agents' records need {2 * n:,} texels of a buffer texture, more than the {self.max_texels:,} "
                              "this GPU allows (GL_MAX_TEXTURE_BUFFER_SIZE): fewer agents")
        size = max(n, 1) * RECORD_DTYPE.itemsize
        if self.buffer.size != size:  # exact: a smaller crowd frees what it no longer needs
            self.buffer.orphan(size)
            self._attach()
        self.agents = n

    def bind(self) -> None:
        """The buffer texture on RECORDS_UNIT, where every draw's program samples it (``u_agents``)."""
        gl = _gl()
        gl["glActiveTexture"](_GL_TEXTURE0 + RECORDS_UNIT)
        gl["glBindTexture"](_GL_TEXTURE_BUFFER, self._texture[0])

    def gpu_bytes(self) -> int:
        return self.buffer.size

    def release(self) -> None:
        if getattr(self, "_texture", None) is not None:
            _gl()["glDeleteTextures"](1, self._texture)
            self._texture = None
        if getattr(self, "buffer", None) is not None:
            self.buffer.release()
            self.buffer = None


class RecordPacker:
    """Packs every agent's record into arrays kept from frame to frame: the palette texel code of agent i
    is a fixed base plus its ring slot's first row, so only that addition runs per frame (the processor
    keeps x under 4096 and its rows under 2^20: texel_code); the character bits are fixed while the cast's
    counts are."""

    def __init__(self, plan: ListPlan, group_names: list[str]):
        self.plan = plan
        self.group_names = list(group_names)
        self._layout: PaletteLayout | None = None

    def _prepare(self, palette: PaletteLayout) -> None:
        n = palette.agents
        self._layout = palette
        self._scratch = np.empty(n, RECORD_DTYPE)
        x, y = palette.texel(np.arange(n), 0, 0)
        self._texel_base = texel_code(x, y)
        kinds = np.repeat(np.arange(len(palette.counts), dtype=np.uint32), palette.counts)
        self._character_bits = kinds << np.uint32(CHARACTER_SHIFT)

    def pack(self, instances: Instances, eye: np.ndarray, row_offset, palette: PaletteLayout) -> np.ndarray:
        """Every agent's record (RECORD_DTYPE (N,), an array owned by the packer: valid until the next call)."""
        n = len(instances)
        if self._layout != palette:
            self._prepare(palette)
        if len(self._scratch) != n:
            raise RecordError(f"{n} instances, but the palette holds {palette.agents} agents")
        records, fields = self._scratch, self._scratch["packed"]
        position = records["position_scale"]
        tint = instances.tint
        packed_tint = tint.dtype == np.uint8 and tint.flags.c_contiguous
        variants = [instances.variant.get(group) for group in self.group_names]
        row_code = texel_code(0, row_offset)
        rgb = np.uint32((1 << CHARACTER_SHIFT) - 1)

        def pack(lo: int, hi: int) -> None:  # agents lo..hi, beside the other spans (crowd.spans)
            # The subtraction in float64 (agents far from the origin), rounded once into the record; a column
            # at a time, which is 3 times as fast as numpy's (N, 3) into strided (N, 3) broadcast.
            for c in range(3):
                np.subtract(instances.position[lo:hi, c], eye[c], out=position[lo:hi, c], casting="unsafe")
            position[lo:hi, 3] = instances.scale[lo:hi]
            np.add(self._texel_base[lo:hi], row_code if row_code.ndim == 0 else row_code[lo:hi], out=fields[lo:hi, 0], casting="unsafe")
            tints = fields[lo:hi, 1]
            tints[:] = tint[lo:hi].view("<u4")[:, 0] if packed_tint else rgba8(tint[lo:hi])
            tints &= rgb
            tints |= self._character_bits[lo:hi]
            write_heading(instances.yaw[lo:hi], fields[lo:hi, 2])
            self.plan.pack_choices(variants, lo, hi, fields[lo:hi, 3])

        over_spans(pack, n)
        return records
