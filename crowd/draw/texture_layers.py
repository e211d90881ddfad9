"""The layers of the crowd's texture arrays, made on the CPU: each image resampled in linear light to
its array's size, its mip levels, and which of them are stored as BC1 (``plan_bc1``).

Which levels: BC1 spends two colours on each 4x4 block, so a coarse mip level, where a block spans
more of the image, fares worse than the full-size level (CesiumMan's level 0 is well within the
bound, its 64x64 level far outside it). A crowd is drawn mostly small, from those levels, so every
level a texture samples is measured: the levels down to the first one over the bound are BC1, and
that level and those below it go to a small RGBA16F array (``MaterialTextures``' "coarse" array),
which the fragment shader reads from that level of detail on. A texture whose level 0, or level 1
with levels below it, is over the bound is not BC1 at all: with level 1 in RGBA16F it would cost
more than 2 bytes a texel.

A texture is within the bound (CIEDE2000 against its linear layer) when the mean is at most
MAX_MEAN_DE, a just-noticeable difference, and 99 % of its texels are within MAX_P99_DE
(docs/BENCHMARKS.md, "Textures", says how the bound was chosen).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from typing import NamedTuple

import numpy as np

from ..asset.model import NEAREST, Texture
from .texture_codec import colour_difference, decode_blocks, decode_bc1, encode_bc1, linear_to_srgb, srgb_to_linear

MAX_LAYER_SIZE = 2048
MAX_ARRAY_BYTES = 256 << 20  # an array with its mip chain; layers are halved until it fits
HALF_TEXEL_BYTES = 8  # RGBA16F
BC1_TEXEL_BYTES = 0.5
MAX_MEAN_DE = 1.0
MAX_P99_DE = 5.0
MEASURED_TEXELS = 1 << 16  # a level is measured on all its texels up to this, past it on the texels of this many / 16 blocks
NEAR = 0.1  # ... and on all its texels where that puts it within this share of a bound (a sample is a few per cent off)
KEPT_BYTES = 64 << 20  # the BC1 plans kept for a renderer built again (a live setting change)
_KEPT: OrderedDict = OrderedDict()
_SRGB8_TO_LINEAR64 = srgb_to_linear(np.arange(256) / 255.0)  # lookups: 8-bit codes only
_SRGB8_TO_LINEAR = _SRGB8_TO_LINEAR64.astype(np.float32)


def layer_size(textures: list[Texture], limit: int = MAX_LAYER_SIZE, budget: int = MAX_ARRAY_BYTES,
               texel_bytes: float = HALF_TEXEL_BYTES) -> tuple[int, int]:
    """(width, height) every layer is stored at: the largest image's, each side at most `limit`, both
    halved until the array (`texel_bytes` a texel, a third more for mip levels) fits `budget` bytes.
    Small images are scaled up to the largest, so many small ones beside one big one would otherwise
    multiply it."""
    w = min(max(t.pixels.shape[1] for t in textures), limit)
    h = min(max(t.pixels.shape[0] for t in textures), limit)
    while len(textures) * w * h * texel_bytes * 4 / 3 > budget and (w > 1 or h > 1):
        w, h = max(w // 2, 1), max(h // 2, 1)
    return w, h


def linear_layer(texture: Texture, size: tuple[int, int]) -> np.ndarray:
    """float32 (H, W, 4): the texture's colour in linear light (alpha as stored), resampled to `size`."""
    rgba = _SRGB8_TO_LINEAR[texture.pixels]
    rgba[..., 3] = texture.pixels[..., 3] / np.float32(255.0)
    w, h = size
    if rgba.shape[:2] == (h, w):
        return rgba
    from PIL import Image

    # Upscaled as the GPU would have filtered the original (bilinear: Lanczos rings and sharpens what
    # was authored soft); reduced with Lanczos. Pillow's resampling clamps at the edges whatever the
    # wrap, which can leave a faint seam on a repeating texture that is resampled.
    if texture.mag_filter == NEAREST:
        method = Image.Resampling.NEAREST
    elif w >= rgba.shape[1] and h >= rgba.shape[0]:
        method = Image.Resampling.BILINEAR
    else:
        method = Image.Resampling.LANCZOS
    return np.clip(_resized(rgba, (w, h), method), 0.0, 1.0).astype(np.float32)


def _resized(image: np.ndarray, size: tuple[int, int], method) -> np.ndarray:
    from PIL import Image

    channels = [np.asarray(Image.fromarray(np.ascontiguousarray(image[..., k], np.float32), mode="F").resize(size, method))
                for k in range(image.shape[2])]
    return np.stack(channels, axis=-1)


def linear_mip_levels(layer: np.ndarray) -> list[np.ndarray]:
    """`layer` (H, W, C, linear light) and each level below it down to 1x1, each the box average of the
    one above (odd sides by area), as glGenerateMipmap makes the RGBA16F array's."""
    from PIL import Image

    levels = [layer]
    while levels[-1].shape[0] > 1 or levels[-1].shape[1] > 1:
        h, w = levels[-1].shape[:2]
        levels.append(_resized(levels[-1], (max(w // 2, 1), max(h // 2, 1)), Image.Resampling.BOX))
    return levels


def bc1_error(linear: np.ndarray, blocks: np.ndarray, sample: int | None = MEASURED_TEXELS) -> tuple[float, float]:
    """(mean, 99th percentile) CIEDE2000 of `blocks` (BC1 of the linear RGB image `linear`) against it;
    on the texels of `sample` // 16 blocks drawn with a fixed seed where the image has more (None: all
    of it). Whole blocks, so that only those are decoded."""
    encoded = np.asarray(blocks, np.uint8).reshape(-1, 8)
    h, w = linear.shape[:2]
    if sample is None or len(encoded) * 16 <= sample:
        # (every texel once: the blocks' padding, which repeats edge texels, left out)
        decoded = _SRGB8_TO_LINEAR64[decode_bc1(encoded, (w, h))]
        return colour_difference(np.asarray(linear[..., :3], np.float64), decoded)
    pick = np.sort(np.random.default_rng(0).choice(len(encoded), sample // 16, replace=False))
    across = -(-w // 4)
    rows = np.minimum(pick[:, None] // across * 4 + np.arange(4), h - 1)  # (the padding repeats the last row and column)
    cols = np.minimum(pick[:, None] % across * 4 + np.arange(4), w - 1)
    reference = np.asarray(linear[rows[:, :, None], cols[:, None, :], :3], np.float64).reshape(-1, 16, 3)
    return colour_difference(reference, _SRGB8_TO_LINEAR64[decode_blocks(encoded[pick])])


def within_bound(error: tuple[float, float]) -> bool:
    return error[0] <= MAX_MEAN_DE and error[1] <= MAX_P99_DE


class BC1Plan(NamedTuple):
    """What ``plan_bc1`` chose, by the index of each image it was given."""

    size: tuple[int, int]  # every BC1 layer's (width, height)
    fine_levels: int  # the mip levels the BC1 array holds; the coarse array holds the rest
    blocks: dict[int, list[bytes]]  # image -> its BC1 blocks, level by level (fine_levels of them)
    coarse: dict[int, np.ndarray]  # image -> its linear level `fine_levels` (H, W, 4) float32, where there is a coarse array
    errors: dict[int, list[tuple[float, float]]]  # image -> (mean, p99) CIEDE2000 of each level tried, at the last size tried


def plan_bc1(images: list[Texture], mip_filtered: list[bool], limit: int = MAX_LAYER_SIZE) -> BC1Plan:
    """Which `images` are BC1 and down to which mip level (see the module docstring); `mip_filtered`:
    whether each image is sampled with mipmaps (only those are measured below level 0). The array's
    size is its largest member's, so when the largest fail, those that passed are encoded again at the
    smaller size and measured again. The last few plans are kept (a renderer rebuilt for a live
    setting gets its textures back without encoding them again)."""
    key = (tuple((hashlib.blake2b(np.ascontiguousarray(t.pixels), digest_size=16).digest(), t.pixels.shape, t.mag_filter == NEAREST)
                 for t in images), tuple(mip_filtered), limit)
    if key in _KEPT:
        _KEPT.move_to_end(key)
        return _KEPT[key]
    mipmapped = any(mip_filtered)
    candidates = list(range(len(images)))
    errors = {}
    while True:
        size = layer_size([images[k] for k in candidates], limit, texel_bytes=BC1_TEXEL_BYTES)
        chains, first_over = {}, {}
        for k in candidates:
            chains[k], errors[k] = _encoded_chain(images[k], size, mipmapped)
            over = [i for i, e in enumerate(errors[k]) if not within_bound(e)]
            first_over[k] = over[0] if over and (mip_filtered[k] or over[0] == 0) else len(errors[k])
        # Level 1 in RGBA16F would cost more than 2 bytes a texel (an image of one level has no level 1).
        passed = [k for k in candidates if first_over[k] >= min(2, len(errors[k]))]
        if not passed or passed == candidates or layer_size([images[k] for k in passed], limit, texel_bytes=BC1_TEXEL_BYTES) == size:
            break
        candidates = passed
    if not passed:
        plan = BC1Plan(size, 0, {}, {}, errors)
    else:
        levels = len(chains[passed[0]][0])
        # (no member sampled with mipmaps: level 0 alone)
        fine = min(first_over[k] for k in passed) if any(mip_filtered[k] for k in passed) else 1
        plan = BC1Plan(size, fine, {k: [b.tobytes() for b in chains[k][1][:fine]] for k in passed},
                       {k: chains[k][0][fine] for k in passed} if fine < levels else {}, errors)
    _KEPT[key] = plan
    while len(_KEPT) > 1 and sum(len(b) for p in _KEPT.values() for chain in p.blocks.values() for b in chain) > KEPT_BYTES:
        _KEPT.popitem(last=False)
    return plan


def forget_plans() -> None:
    """Drop the kept plans (the next ``plan_bc1`` encodes, as a first load does)."""
    _KEPT.clear()


def _encoded_chain(image: Texture, size: tuple[int, int], mipmapped: bool):
    """([linear level (H, W, 4)], [BC1 blocks of each level], [(mean, p99) of each level]) of `image` at `size`."""
    layer = linear_layer(image, size)
    levels = linear_mip_levels(layer) if mipmapped else [layer]
    blocks, errors = [], []
    for i, level in enumerate(levels):
        # A layer at its image's own size encodes the image's own codes (no round trip through light).
        own = i == 0 and image.pixels.shape[:2] == level.shape[:2]
        codes = image.pixels[..., :3].astype(np.float32) if own else linear_to_srgb(level[..., :3]) * 255.0
        blocks.append(encode_bc1(codes))
        error = bc1_error(level, blocks[-1])
        if abs(error[0] / MAX_MEAN_DE - 1) < NEAR or abs(error[1] / MAX_P99_DE - 1) < NEAR:
            error = bc1_error(level, blocks[-1], sample=None)  # a sample's few per cent decide nothing here
        errors.append(error)
    return (levels, blocks), errors
