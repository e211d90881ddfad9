"""The crowd's base-colour textures on the GPU: one texture array and one sampler object per texture.

Why one array: every piece of every agent is one instanced draw per (piece, LOD); a texture array lets
the draws of all pieces share one binding, and a piece picks its layer with one uniform. Layers of an
array share one size, so each image is resampled to the largest image's size (at most MAX_LAYER_SIZE);
this is done in linear light, per channel, with Pillow, and pixel-art textures (magnified NEAREST) are
resampled NEAREST so their pixels stay square.

Why sampler objects: each glTF texture carries its own wrap and filter, and a sampler object binds
them to the array at draw time (GL 3.3 core). GL's MIRRORED_REPEAT has no moderngl switch, so the
shader folds the coordinate into [0, 1] (``u_uv_mirror``) and the sampler clamps that axis, so
filtering at a fold blends the edge texel with itself as GL's mirrored repeat does (a repeating
sampler would blend it with the opposite edge); the unfolded coordinate's derivatives keep the mip
level smooth across the fold.

Storage: RGBA16F holding linear colour. moderngl cannot make an sRGB texture array, and decoding sRGB
after filtering would darken every filtered edge (a black-white edge half way reads 0.21 instead of
0.5); half floats filter and mipmap in linear light and hold 8-bit sRGB's darkest step (1.2e-3 relative
precision against sRGB's 0.5 %) at twice its bytes, which ``gpu_bytes`` reports.
"""

from __future__ import annotations

import moderngl
import numpy as np

from ..asset.model import MIPMAP_FILTERS, MIRRORED_REPEAT, NEAREST, REPEAT, Texture
from ..gl import GLObjects, GLStage

MAX_LAYER_SIZE = 2048
MAX_ARRAY_BYTES = 256 << 20  # the array with its mip chain; layers are halved until it fits
TEXTURE_UNIT = 6  # units 0-2: the palette, 3: the shadow map; the processor's pass uses 0-5


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """The sRGB transfer function's inverse (IEC 61966-2-1), float64 in [0, 1]."""
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


_SRGB8_TO_LINEAR = srgb_to_linear(np.arange(256) / 255.0).astype(np.float32)  # a lookup: 8-bit codes only


def layer_size(textures: list[Texture], limit: int = MAX_LAYER_SIZE, budget: int = MAX_ARRAY_BYTES) -> tuple[int, int]:
    """(width, height) every layer is stored at: the largest image's, each side at most `limit`, both
    halved until the array (RGBA16F, a third more for mip levels) fits `budget` bytes. Small images
    are scaled up to the largest, so many small ones beside one big one would otherwise multiply it."""
    w = min(max(t.pixels.shape[1] for t in textures), limit)
    h = min(max(t.pixels.shape[0] for t in textures), limit)
    while len(textures) * w * h * 8 * 4 // 3 > budget and (w > 1 or h > 1):
        w, h = max(w // 2, 1), max(h // 2, 1)
    return w, h


def linear_layer(texture: Texture, size: tuple[int, int]) -> np.ndarray:
    """float32 (H, W, 4): the texture's colour in linear light (alpha as stored), resampled to `size`."""
    from PIL import Image

    rgba = _SRGB8_TO_LINEAR[texture.pixels]
    rgba[..., 3] = texture.pixels[..., 3] / np.float32(255.0)
    w, h = size
    if rgba.shape[:2] == (h, w):
        return rgba
    # Upscaled as the GPU would have filtered the original (bilinear: Lanczos rings and sharpens what
    # was authored soft); reduced with Lanczos. Pillow's resampling clamps at the edges whatever the
    # wrap, which can leave a faint seam on a repeating texture that is resampled.
    if texture.mag_filter == NEAREST:
        method = Image.Resampling.NEAREST
    elif w >= rgba.shape[1] and h >= rgba.shape[0]:
        method = Image.Resampling.BILINEAR
    else:
        method = Image.Resampling.LANCZOS
    channels = [np.asarray(Image.fromarray(np.ascontiguousarray(rgba[..., k]), mode="F").resize((w, h), method)) for k in range(4)]
    return np.clip(np.stack(channels, axis=-1), 0.0, 1.0).astype(np.float32)


class MaterialTextures(GLStage):
    """The texture array and the samplers of the textures that the drawn pieces use (only those)."""

    def __init__(self, ctx: moderngl.Context, textures: list[Texture], used):
        self._objects = GLObjects()
        self.layers: dict[int, int] = {}  # texture index -> layer
        images: list[Texture] = []  # one per distinct image
        by_image: dict[int, int] = {}
        for t in sorted(set(used)):
            key = id(textures[t].pixels)  # textures sharing one image share one layer (model.Texture)
            if key not in by_image:
                by_image[key] = len(images)
                images.append(textures[t])
            self.layers[t] = by_image[key]
        if not images:
            raise ValueError("MaterialTextures needs at least one used texture")
        limit = min(MAX_LAYER_SIZE, int(ctx.info.get("GL_MAX_TEXTURE_SIZE", MAX_LAYER_SIZE)))
        max_layers = int(ctx.info.get("GL_MAX_ARRAY_TEXTURE_LAYERS", 256))
        if len(images) > max_layers:
            raise ValueError(f"{len(images)} textures, more than the {max_layers} layers this GPU's texture arrays hold")
        self.size = layer_size(images, limit)
        data = np.stack([linear_layer(t, self.size) for t in images]).astype(np.float16)
        self.array = self._objects.add(ctx.texture_array((*self.size, len(images)), 4, data.tobytes(), dtype="f2"))
        self.mipmapped = any(textures[t].min_filter in MIPMAP_FILTERS for t in self.layers)
        if self.mipmapped:
            self.array.build_mipmaps()
        self.array.extra = {"mipmapped": self.mipmapped}
        self.samplers: dict[int, moderngl.Sampler] = {}
        self.mirror: dict[int, tuple[float, float]] = {}
        for t in self.layers:
            tex = textures[t]
            minify = tex.min_filter if self.mipmapped or tex.min_filter not in MIPMAP_FILTERS else tex.mag_filter
            self.samplers[t] = self._objects.add(ctx.sampler(
                repeat_x=tex.wrap[0] == REPEAT, repeat_y=tex.wrap[1] == REPEAT, filter=(minify, tex.mag_filter)))
            self.mirror[t] = (float(tex.wrap[0] == MIRRORED_REPEAT), float(tex.wrap[1] == MIRRORED_REPEAT))

    def bind(self, texture: int, prog: moderngl.Program) -> None:
        """Bind `texture`'s layer and sampler for the next draw with `prog`."""
        self.array.use(TEXTURE_UNIT)
        self.samplers[texture].use(TEXTURE_UNIT)
        prog["u_layer"] = float(self.layers[texture])
        if "u_uv_mirror" in prog:
            prog["u_uv_mirror"] = self.mirror[texture]

    def unbind(self) -> None:
        """Leave unit TEXTURE_UNIT without a sampler object, which would override any texture bound there later."""
        next(iter(self.samplers.values())).clear(TEXTURE_UNIT)

    def gpu_bytes(self) -> int:
        return self._objects.gpu_bytes()

    def release(self) -> None:
        if hasattr(self, "_objects"):
            self._objects.release()
