"""The crowd's base-colour textures on the GPU: texture arrays and one sampler object per texture.

Why arrays: every piece of every agent is one instanced draw per (piece, LOD); a texture array lets
the draws of many pieces share one binding, and a piece picks its layer with one uniform. Layers of an
array share one size, so each image is resampled to the largest image's size in its array (at most
MAX_LAYER_SIZE; ``texture_layers``).

Up to three arrays, by how a texture is stored:
- **"bc1"**: BC1 blocks with sRGB ends (``texture_codec``; EXT_texture_compression_s3tc, on Mesa,
  NVIDIA, AMD, Intel and macOS's 4.1 core alike), half a byte a texel. The GPU decodes a block to sRGB
  codes and those to linear light before it filters, so filtering mixes light. It holds each texture's
  mip levels down to the first whose error is over the bound (``texture_layers.plan_bc1``); GL cannot
  make a compressed format's mip levels, so they are made on the CPU in linear light and encoded.
- **"coarse"**: the BC1 textures' levels from there down, in RGBA16F, a sixteenth of the texels or
  fewer. The fragment shader reads it past that level of detail (``u_coarse_lod``), blending the
  two arrays across one level as trilinear filtering blends two levels.
- **"rgba16f"**: linear colour, for every texture whose level 0 or 1 is over the bound, where the
  driver lacks the BC1 formats, or with compression off. moderngl cannot make an sRGB texture array,
  and decoding sRGB after filtering would darken every filtered edge (a black-white edge half way reads
  0.21 instead of 0.5); half floats filter and mipmap in linear light and hold 8-bit sRGB's darkest
  step at 8 bytes a texel.
``gpu_bytes`` counts all three, mip levels included.

Why sampler objects: each glTF texture carries its own wrap and filter, and a sampler object binds
them to the array at draw time (GL 3.3 core). GL's MIRRORED_REPEAT has no moderngl switch, so the
shader folds the coordinate into [0, 1] (``u_uv_mirror``) and the sampler clamps that axis, so
filtering at a fold blends the edge texel with itself as GL's mirrored repeat does (a repeating
sampler would blend it with the opposite edge); the unfolded coordinate's derivatives keep the mip
level smooth across the fold.
"""

from __future__ import annotations

import ctypes

import moderngl
import numpy as np

from ..asset.model import MIPMAP_FILTERS, MIRRORED_REPEAT, REPEAT, Texture
from ..gl import GLObjects, GLStage, current_context_function, has_uniform
from .texture_layers import MAX_LAYER_SIZE, layer_size, linear_layer, plan_bc1

TEXTURE_UNIT = 6  # units 0-2: the palette, 3: the shadow map; the processor's pass uses 0-5
COARSE_UNIT = 11  # after the impostors' 8-10 and the pyramid's 7
NEVER = 1e9  # a u_coarse_lod no level of detail reaches
S3TC_EXTENSION = "GL_EXT_texture_compression_s3tc"
COMPRESSED_SRGB_S3TC_DXT1 = 0x8C4C  # EXT_texture_sRGB's enum (core profiles that list no EXT_texture_sRGB accept it too)


def bc1_unavailable(ctx: moderngl.Context) -> str:
    """Why `ctx` cannot hold BC1 textures, in a few words; "" where it can (the format itself is
    checked again when the array is made)."""
    return "" if S3TC_EXTENSION in ctx.extensions else f"the driver lacks {S3TC_EXTENSION}"


class BlockFormatRefused(RuntimeError):
    """The driver did not store a compressed array in the format asked for."""


class BlockArray:
    """A texture array of BC1 blocks with sRGB ends. moderngl has no compressed upload, so the texture
    is made and bound through GL 3.0 core entry points (``current_context_function``); these touch no
    state moderngl caches (it binds a texture's unit itself every time it uses one)."""

    _TEXTURE_2D_ARRAY = 0x8C1A
    _TEXTURE0 = 0x84C0
    _PIXEL_UNPACK_BUFFER = 0x88EC
    _MAX_LEVEL = 0x813D
    _INTERNAL_FORMAT = 0x1003
    _COMPRESSED = 0x86A1

    def __init__(self, size: tuple[int, int], layers: int, levels: list[bytes], unit: int = TEXTURE_UNIT):
        """`levels`: each mip level's blocks, every layer's in turn, from the full size down."""
        c, i, p = ctypes.c_uint, ctypes.c_int, ctypes.c_void_p
        types = {"glGenTextures": (None, i, ctypes.POINTER(c)), "glDeleteTextures": (None, i, ctypes.POINTER(c)),
                 "glActiveTexture": (None, c), "glBindTexture": (None, c, c), "glBindBuffer": (None, c, c),
                 "glTexParameteri": (None, c, c, i), "glCompressedTexImage3D": (None, c, i, c, i, i, i, i, i, p),
                 "glGetTexLevelParameteriv": (None, c, i, c, ctypes.POINTER(i)), "glGetError": (c,)}
        self._gl = {name: current_context_function(name, ctypes.CFUNCTYPE(*sig)) for name, sig in types.items()}
        self.size, self.layers, self.levels = size, layers, len(levels)
        self.nbytes = sum(len(level) for level in levels)
        name = ctypes.c_uint(0)
        self._gl["glGenTextures"](1, ctypes.byref(name))
        self.name = name.value
        self.use(unit)
        self._gl["glBindBuffer"](self._PIXEL_UNPACK_BUFFER, 0)  # a bound unpack buffer would make the pointer an offset
        self._gl["glTexParameteri"](self._TEXTURE_2D_ARRAY, self._MAX_LEVEL, len(levels) - 1)
        for level, data in enumerate(levels):
            w, h = max(size[0] >> level, 1), max(size[1] >> level, 1)
            self._gl["glCompressedTexImage3D"](self._TEXTURE_2D_ARRAY, level, COMPRESSED_SRGB_S3TC_DXT1, w, h, layers, 0, len(data),
                                               ctypes.create_string_buffer(data, len(data)))
        stored, compressed = ctypes.c_int(0), ctypes.c_int(0)
        self._gl["glGetTexLevelParameteriv"](self._TEXTURE_2D_ARRAY, 0, self._INTERNAL_FORMAT, ctypes.byref(stored))
        self._gl["glGetTexLevelParameteriv"](self._TEXTURE_2D_ARRAY, 0, self._COMPRESSED, ctypes.byref(compressed))
        if stored.value != COMPRESSED_SRGB_S3TC_DXT1 or not compressed.value:
            error = self._gl["glGetError"]()  # taken off the queue, so no later check blames another call
            self.release()
            raise BlockFormatRefused(f"the driver refused the sRGB BC1 format {COMPRESSED_SRGB_S3TC_DXT1:#x} (GL error {error:#x})")

    def use(self, unit: int) -> None:
        self._gl["glActiveTexture"](self._TEXTURE0 + unit)
        self._gl["glBindTexture"](self._TEXTURE_2D_ARRAY, self.name)

    def release(self) -> None:
        if getattr(self, "name", 0):
            self._gl["glDeleteTextures"](1, ctypes.byref(ctypes.c_uint(self.name)))
            self.name = 0


class MaterialTextures(GLStage):
    """The texture arrays and the samplers of the textures that the drawn pieces use (only those).
    `compress`: False keeps every texture in "rgba16f"."""

    def __init__(self, ctx: moderngl.Context, textures: list[Texture], used, compress: bool = True):
        self._objects = GLObjects()
        self.layers: dict[int, int] = {}  # texture index -> layer of its array
        self.storage: dict[int, str] = {}  # texture index -> "bc1" or "rgba16f"
        self.errors: dict[int, list[tuple[float, float]]] = {}  # texture index -> (mean, p99) CIEDE2000 of each BC1 level tried
        self.arrays: dict[str, moderngl.TextureArray | BlockArray] = {}  # "bc1", "coarse", "rgba16f": those in use
        self.mipmapped: dict[str, bool] = {}  # by array
        self.coarse_lod = NEVER  # the level of detail from which BC1 textures read the "coarse" array
        self.notes: list[str] = []  # one line for each thing that kept textures out of BC1 other than their error
        images: list[Texture] = []  # one per distinct image
        image_of: dict[int, int] = {}
        by_image: dict[int, int] = {}
        for t in sorted(set(used)):
            key = id(textures[t].pixels)  # textures sharing one image share one layer (model.Texture)
            if key not in by_image:
                by_image[key] = len(images)
                images.append(textures[t])
            image_of[t] = by_image[key]
        if not images:
            raise ValueError("MaterialTextures needs at least one used texture")
        limit = min(MAX_LAYER_SIZE, int(ctx.info.get("GL_MAX_TEXTURE_SIZE", MAX_LAYER_SIZE)))
        max_layers = int(ctx.info.get("GL_MAX_ARRAY_TEXTURE_LAYERS", 256))
        if len(images) > max_layers:
            raise ValueError(f"{len(images)} textures, more than the {max_layers} layers this GPU's texture arrays hold")
        mip_filtered = [any(textures[t].min_filter in MIPMAP_FILTERS for t in image_of if image_of[t] == k) for k in range(len(images))]

        order = {"bc1": [], "rgba16f": list(range(len(images)))}
        why = bc1_unavailable(ctx) if compress else ""
        if why:
            self.notes.append(f"textures kept in RGBA16F: {why}")
        elif compress:
            plan = plan_bc1(images, mip_filtered, limit)
            for t, k in image_of.items():
                if k in plan.errors:
                    self.errors[t] = plan.errors[k]
            if plan.blocks:
                try:
                    self._make_bc1(ctx, plan)
                    order = {"bc1": sorted(plan.blocks), "rgba16f": [k for k in range(len(images)) if k not in plan.blocks]}
                except BlockFormatRefused as exc:
                    self.notes.append(f"textures kept in RGBA16F: {exc}")
        if order["rgba16f"]:
            subset = [images[k] for k in order["rgba16f"]]
            size = layer_size(subset, limit)
            data = np.stack([linear_layer(t, size) for t in subset]).astype(np.float16)
            self.mipmapped["rgba16f"] = any(mip_filtered[k] for k in order["rgba16f"])
            self.arrays["rgba16f"] = self._half_array(ctx, size, data, self.mipmapped["rgba16f"])
        for t, k in image_of.items():
            self.storage[t] = "bc1" if k in order["bc1"] else "rgba16f"
            self.layers[t] = order[self.storage[t]].index(k)

        self.samplers: dict[int, moderngl.Sampler] = {}
        self.mirror: dict[int, tuple[float, float]] = {}
        for t in self.layers:
            tex = textures[t]
            minify = tex.min_filter if self.mipmapped[self.storage[t]] or tex.min_filter not in MIPMAP_FILTERS else tex.mag_filter
            self.samplers[t] = self._objects.add(ctx.sampler(
                repeat_x=tex.wrap[0] == REPEAT, repeat_y=tex.wrap[1] == REPEAT, filter=(minify, tex.mag_filter)))
            self.mirror[t] = (float(tex.wrap[0] == MIRRORED_REPEAT), float(tex.wrap[1] == MIRRORED_REPEAT))

    def _make_bc1(self, ctx: moderngl.Context, plan) -> None:
        """The "bc1" array of the plan's images, in their order, and its "coarse" array where it has one."""
        members = sorted(plan.blocks)
        array = BlockArray(plan.size, len(members), [b"".join(plan.blocks[k][level] for k in members) for level in range(plan.fine_levels)])
        self.arrays["bc1"] = self._objects.add(array)
        self.mipmapped["bc1"] = plan.fine_levels > 1
        if plan.coarse:
            first = plan.coarse[members[0]]
            data = np.stack([plan.coarse[k] for k in members]).astype(np.float16)
            self.arrays["coarse"] = self._half_array(ctx, (first.shape[1], first.shape[0]), data, True)
            self.coarse_lod = float(plan.fine_levels)

    def _half_array(self, ctx: moderngl.Context, size: tuple[int, int], data: np.ndarray, mipmapped: bool) -> moderngl.TextureArray:
        array = self._objects.add(ctx.texture_array((*size, len(data)), 4, data.tobytes(), dtype="f2"))
        if mipmapped:
            array.build_mipmaps()
        array.extra = {"mipmapped": mipmapped}
        return array

    def bind(self, texture: int, prog: moderngl.Program) -> None:
        """Bind `texture`'s arrays, layer and sampler for the next draw with `prog`."""
        storage = self.storage[texture]
        array = self.arrays[storage]
        array.use(TEXTURE_UNIT)
        self.samplers[texture].use(TEXTURE_UNIT)
        prog["u_layer"] = float(self.layers[texture])
        if has_uniform(prog, "u_uv_mirror"):
            prog["u_uv_mirror"] = self.mirror[texture]
        if has_uniform(prog, "u_coarse_lod"):
            coarse = storage == "bc1" and "coarse" in self.arrays
            prog["u_coarse_lod"] = self.coarse_lod if coarse else NEVER
            prog["u_albedo_size"] = tuple(float(x) for x in array.size[:2])
            prog["u_albedo_coarse"] = COARSE_UNIT
            if coarse:
                self.arrays["coarse"].use(COARSE_UNIT)
                self.samplers[texture].use(COARSE_UNIT)

    def unbind(self) -> None:
        """Leave the units without a sampler object, which would override any texture bound there later."""
        sampler = next(iter(self.samplers.values()))
        sampler.clear(TEXTURE_UNIT)
        sampler.clear(COARSE_UNIT)

    def gpu_bytes(self) -> int:
        """Bytes of the arrays with their mip levels (BC1's are whole 4x4 blocks of 8 bytes)."""
        return self._objects.gpu_bytes() + sum(a.nbytes for a in self.arrays.values() if isinstance(a, BlockArray))

    def release(self) -> None:
        if hasattr(self, "_objects"):
            self._objects.release()
