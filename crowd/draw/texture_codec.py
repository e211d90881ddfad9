"""Base-colour images as BC1 blocks with sRGB endpoints, and how far a decoded texel is from its source.

BC1 (S3TC's DXT1) stores each 4x4 block of texels in 8 bytes: two RGB565 end colours and a 2-bit index
a texel, the index choosing an end or one of the two colours a third of the way between them. With an
sRGB format (EXT_texture_sRGB's COMPRESSED_SRGB_S3TC_DXT1) the block is decoded to sRGB codes and then
to linear light before the sampler filters, so filtering mixes light as the RGBA16F array does, at half
a byte a texel instead of 8. The encoder works in sRGB codes, where a step is about as visible at
either end of the scale, and returns what the GPU will decode (``decode_bc1``) so that the error can be
measured before the texture is trusted to it (``colour_difference``: CIEDE2000).

Alpha is not kept: the shading reads a base colour's RGB only (alpha modes are left out at import).

Why by hand: the packages that encode BCn (etcpak, quicktex) are compiled extensions, a wheel per
platform and Python version; this encoder is 150 lines of vectorised numpy whose blocks are decoded and
measured here anyway, and its load time is in docs/BENCHMARKS.md ("Textures at half a byte a texel").
"""

from __future__ import annotations

import numpy as np

from ..spans import over_spans

BLOCK = 4  # texels a side
BLOCK_BYTES = 8
CHUNK_BLOCKS = 1 << 15  # blocks encoded together: the index search holds (chunk, 16, 4) distances
REFINE_STEPS = 2  # least-squares passes over each block's ends; a third changes the error little (docs/BENCHMARKS.md)
_THIRDS = np.array([1.0, 0.0, 2.0 / 3.0, 1.0 / 3.0], np.float32)  # the share of end 0 in palette entries 0-3


def srgb_to_linear(c) -> np.ndarray:
    """The sRGB transfer function's inverse (IEC 61966-2-1), float64 in [0, 1]."""
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c) -> np.ndarray:
    """The sRGB transfer function, in [0, 1]; float32 stays float32 (twice as fast, for whole images)."""
    c = np.asarray(c)
    c = np.clip(c if c.dtype == np.float32 else c.astype(np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * c ** (1.0 / 2.4) - 0.055).astype(c.dtype)


# -- BC1


def _expand(q: np.ndarray, bits: int) -> np.ndarray:
    """A 5- or 6-bit colour field as the 8-bit code GL decodes it to (its top bits repeated below)."""
    return (q << (8 - bits)) | (q >> (2 * bits - 8))


def _third(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(2a + b) / 3 rounded, in 8-bit codes: the palette entry two thirds of the way to `a`."""
    return (2 * a + b + 1) // 3


def _single_colour_tables() -> dict[int, np.ndarray]:
    """Per field width, for each 8-bit code v: the (end 0, end 1) fields whose two-thirds entry is
    nearest v. A flat area then decodes to within a code or two of its colour, where the nearest 565
    colour alone can be 4 codes off in red and blue (and a region of one colour is what atlases hold)."""
    tables = {}
    for bits in (5, 6):
        q = np.arange(1 << bits)
        e = _expand(q, bits)
        value = _third(e[:, None], e[None, :])  # (a, b)
        cost = np.abs(value[None, :, :] - np.arange(256)[:, None, None])
        best = cost.reshape(256, -1).argmin(axis=1)
        tables[bits] = np.stack([best // (1 << bits), best % (1 << bits)], axis=1)
    return tables


_SINGLE = _single_colour_tables()


def _quantise(colour: np.ndarray) -> np.ndarray:
    """Float codes (..., 3) to 565 fields (..., 3) int32, each the nearest."""
    c = np.clip(colour, 0.0, 255.0)
    return np.stack([np.rint(c[..., 0] * 31 / 255), np.rint(c[..., 1] * 63 / 255), np.rint(c[..., 2] * 31 / 255)], axis=-1).astype(np.int32)


def _decoded_ends(fields: np.ndarray) -> np.ndarray:
    return np.stack([_expand(fields[..., 0], 5), _expand(fields[..., 1], 6), _expand(fields[..., 2], 5)], axis=-1)


def _packed(fields: np.ndarray) -> np.ndarray:
    return (fields[..., 0] << 11) | (fields[..., 1] << 5) | fields[..., 2]


def _palette(end0: np.ndarray, end1: np.ndarray) -> np.ndarray:
    """(blocks, 4, 3) int32 codes of four-colour mode's palette (the caller keeps end 0 above end 1)."""
    return np.stack([end0, end1, _third(end0, end1), _third(end1, end0)], axis=1)


def _fit(texels: np.ndarray, fields0: np.ndarray, fields1: np.ndarray):
    """Each texel's nearest palette entry for ends (fields0, fields1); returns (indices, the block's
    squared error less its texels' own squared length, which is the same whatever the ends).
    Plain squared error in sRGB codes: weighting the channels by their share of luminance measured
    worse under CIEDE2000 (docs/BENCHMARKS.md)."""
    palette = _palette(_decoded_ends(fields0), _decoded_ends(fields1)).astype(np.float32)
    # |x - p|^2 = |x|^2 - 2 x.p + |p|^2: one batched product instead of a (blocks, 16, 4, 3) difference.
    dist = (palette * palette).sum(-1)[:, None, :] - 2 * np.matmul(texels, palette.transpose(0, 2, 1))
    indices = dist.argmin(axis=2)
    return indices, np.take_along_axis(dist, indices[..., None], axis=2)[..., 0].sum(axis=1)


def _least_squares_ends(texels: np.ndarray, indices: np.ndarray, end0: np.ndarray, end1: np.ndarray):
    """The two ends that fit the texels best in the least-squares sense for the given indices (float
    codes); blocks whose indices all share one weight keep their ends."""
    alpha = _THIRDS[indices]  # (blocks, 16): each texel's share of end 0
    shares = np.stack([alpha, 1.0 - alpha], axis=1)  # (blocks, 2, 16)
    normal = np.matmul(shares, shares.transpose(0, 2, 1))  # (blocks, 2, 2)
    right = np.matmul(shares, texels)  # (blocks, 2, 3)
    aa, ab, bb = normal[:, 0, 0], normal[:, 0, 1], normal[:, 1, 1]
    det = aa * bb - ab * ab
    ok = det > 1e-3
    safe = np.where(ok, det, 1.0)[:, None]
    new0 = (bb[:, None] * right[:, 0] - ab[:, None] * right[:, 1]) / safe
    new1 = (aa[:, None] * right[:, 1] - ab[:, None] * right[:, 0]) / safe
    return np.where(ok[:, None], new0, end0), np.where(ok[:, None], new1, end1)


def _encode_blocks(texels: np.ndarray) -> np.ndarray:
    """(blocks, 16, 3) float32 sRGB codes to (blocks, 8) uint8 BC1 blocks."""
    n = texels.shape[0]
    mean = texels.mean(axis=1)
    centred = texels - mean[:, None, :]
    # The principal axis of each block's colours (power iteration on the covariance), its ends where the
    # texels' projections end. It starts from the covariance's column of the most varied channel, which
    # has a share of the principal axis unless the block is flat (a start such as the brightest minus
    # the darkest texel can be square to it: a red-to-green ramp keeps R + G constant).
    cov = np.matmul(centred.transpose(0, 2, 1), centred)
    axis = np.take_along_axis(cov, np.argmax(np.diagonal(cov, axis1=1, axis2=2), axis=1)[:, None, None], axis=2)[..., 0]
    axis += np.float32(1e-6)  # (a flat block: any axis)
    for _ in range(4):
        axis = np.matmul(cov, axis[..., None])[..., 0]
        axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
    t = np.matmul(centred, axis[..., None])[..., 0]
    end0 = mean + t.max(1)[:, None] * axis
    end1 = mean + t.min(1)[:, None] * axis

    best0, best1 = _quantise(end0), _quantise(end1)
    best_idx, best_err = _fit(texels, *_ordered(best0, best1))
    for _ in range(REFINE_STEPS):
        f0, f1 = _ordered(best0, best1)
        end0, end1 = _least_squares_ends(texels, best_idx, _decoded_ends(f0).astype(np.float32), _decoded_ends(f1).astype(np.float32))
        q0, q1 = _quantise(end0), _quantise(end1)
        idx, err = _fit(texels, *_ordered(q0, q1))
        better = err < best_err
        best0[better], best1[better], best_idx[better], best_err[better] = q0[better], q1[better], idx[better], err[better]
    # A block of one colour (or nearly): the table's pair, read through the entry a third of the way.
    codes = np.clip(np.rint(mean), 0, 255).astype(np.int32)
    s0 = np.stack([_SINGLE[5][codes[:, 0], 0], _SINGLE[6][codes[:, 1], 0], _SINGLE[5][codes[:, 2], 0]], axis=1)
    s1 = np.stack([_SINGLE[5][codes[:, 0], 1], _SINGLE[6][codes[:, 1], 1], _SINGLE[5][codes[:, 2], 1]], axis=1)
    idx, err = _fit(texels, *_ordered(s0, s1))
    better = err < best_err
    best0[better], best1[better], best_idx[better] = s0[better], s1[better], idx[better]

    f0, f1 = _ordered(best0, best1)
    p0, p1 = _packed(f0), _packed(f1)
    indices = best_idx
    # _fit ranked the palette of the ordered ends; a block whose ends are equal is in three-colour mode,
    # where entry 3 is black: every texel there takes entry 0 (all four entries are that one colour).
    indices = np.where((p0 == p1)[:, None], 0, indices)
    words = (indices.astype(np.uint32) << (2 * np.arange(16, dtype=np.uint32))).sum(axis=1, dtype=np.uint32)
    out = np.empty((n, BLOCK_BYTES), np.uint8)
    out[:, 0:2] = p0.astype("<u2").view(np.uint8).reshape(n, 2)
    out[:, 2:4] = p1.astype("<u2").view(np.uint8).reshape(n, 2)
    out[:, 4:8] = words.astype("<u4").view(np.uint8).reshape(n, 4)
    return out


def _ordered(fields0: np.ndarray, fields1: np.ndarray):
    """The ends with end 0 the larger 565 word, as four-colour mode needs (swapping the ends only
    mirrors the palette, and the index search runs after this)."""
    swap = _packed(fields0) < _packed(fields1)
    return np.where(swap[:, None], fields1, fields0), np.where(swap[:, None], fields0, fields1)


def encode_bc1(srgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) sRGB codes (float, 0 to 255) to BC1 blocks: uint8 (ceil(H/4) * ceil(W/4) * 8,), blocks
    row by row, each as GL's COMPRESSED_SRGB_S3TC_DXT1 reads it. Deterministic: the same image gives the
    same bytes."""
    blocks = _blocks_of(np.asarray(srgb, np.float32)[..., :3])
    out = np.empty((len(blocks), BLOCK_BYTES), np.uint8)

    def encode_span(lo: int, hi: int) -> None:  # blocks are independent: spans of them run in threads
        for i in range(lo, hi, CHUNK_BLOCKS):
            out[i:min(i + CHUNK_BLOCKS, hi)] = _encode_blocks(blocks[i:min(i + CHUNK_BLOCKS, hi)])

    over_spans(encode_span, len(blocks), min_span=CHUNK_BLOCKS)
    return out.reshape(-1)


def decode_blocks(blocks: np.ndarray) -> np.ndarray:
    """BC1 blocks (n, 8) uint8 to their texels (n, 16, 3) uint8 sRGB codes, row by row within a block,
    as ``encode_bc1`` wrote them (GPUs round the thirds within a code of this)."""
    blocks = np.ascontiguousarray(blocks, np.uint8)
    p0 = blocks[:, 0:2].copy().view("<u2")[:, 0].astype(np.int32)
    p1 = blocks[:, 2:4].copy().view("<u2")[:, 0].astype(np.int32)
    words = blocks[:, 4:8].copy().view("<u4")[:, 0].astype(np.int64)

    def ends(p):
        return np.stack([_expand(p >> 11, 5), _expand((p >> 5) & 63, 6), _expand(p & 31, 5)], axis=-1)

    e0, e1 = ends(p0), ends(p1)
    four = _palette(e0, e1)
    three = np.stack([e0, e1, (e0 + e1) // 2, np.zeros_like(e0)], axis=1)
    palette = np.where((p0 > p1)[:, None, None], four, three)
    indices = (words[:, None] >> (2 * np.arange(16))) & 3
    return np.take_along_axis(palette, indices[..., None], axis=1).astype(np.uint8)


def decode_bc1(data: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """BC1 blocks of an image of `size` (width, height) to its (H, W, 3) uint8 sRGB codes."""
    w, h = size
    bh, bw = -(-h // BLOCK), -(-w // BLOCK)
    texels = decode_blocks(np.asarray(data, np.uint8).reshape(bh * bw, BLOCK_BYTES))
    image = texels.reshape(bh, bw, BLOCK, BLOCK, 3).transpose(0, 2, 1, 3, 4).reshape(bh * BLOCK, bw * BLOCK, 3)
    return image[:h, :w]


def _blocks_of(image: np.ndarray) -> np.ndarray:
    """(H, W, C) to (blocks, 16, C), row-major blocks, the edges repeated out to whole blocks."""
    h, w, c = image.shape
    bh, bw = -(-h // BLOCK), -(-w // BLOCK)
    if (bh * BLOCK, bw * BLOCK) != (h, w):
        image = np.pad(image, ((0, bh * BLOCK - h), (0, bw * BLOCK - w), (0, 0)), mode="edge")
    return image.reshape(bh, BLOCK, bw, BLOCK, c).transpose(0, 2, 1, 3, 4).reshape(bh * bw, BLOCK * BLOCK, c)


def bc1_bytes(size: tuple[int, int]) -> int:
    """Bytes of one BC1 image of `size` (width, height): whole blocks."""
    return -(-size[0] // BLOCK) * -(-size[1] // BLOCK) * BLOCK_BYTES


# -- colour difference


_LINEAR_TO_XYZ = np.array([[0.4124564, 0.3575761, 0.1804375],
                           [0.2126729, 0.7151522, 0.0721750],
                           [0.0193339, 0.1191920, 0.9503041]])  # sRGB primaries, D65 white
_D65 = _LINEAR_TO_XYZ.sum(axis=1)


def linear_to_lab(rgb: np.ndarray) -> np.ndarray:
    """Linear sRGB (..., 3) to CIELAB (..., 3) under D65, float64."""
    xyz = np.asarray(rgb, np.float64)[..., :3] @ _LINEAR_TO_XYZ.T / _D65
    eps = (6 / 29) ** 3
    f = np.where(xyz > eps, np.cbrt(np.maximum(xyz, eps)), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], axis=-1)


def ciede2000(lab1: np.ndarray, lab2: np.ndarray) -> np.ndarray:
    """CIEDE2000 colour difference of CIELAB pairs (..., 3), kL = kC = kH = 1 (Sharma, Wu and Dalal, 2005)."""
    l1, a1, b1 = np.moveaxis(np.asarray(lab1, np.float64), -1, 0)
    l2, a2, b2 = np.moveaxis(np.asarray(lab2, np.float64), -1, 0)
    c_mean = (np.hypot(a1, b1) + np.hypot(a2, b2)) / 2
    g = 0.5 * (1 - np.sqrt(c_mean ** 7 / (c_mean ** 7 + 25.0 ** 7)))
    a1p, a2p = (1 + g) * a1, (1 + g) * a2
    c1p, c2p = np.hypot(a1p, b1), np.hypot(a2p, b2)
    h1p = np.where(c1p == 0, 0.0, np.degrees(np.arctan2(b1, a1p)) % 360)
    h2p = np.where(c2p == 0, 0.0, np.degrees(np.arctan2(b2, a2p)) % 360)
    dl, dc = l2 - l1, c2p - c1p
    dh = h2p - h1p
    dh = np.where(dh > 180, dh - 360, np.where(dh < -180, dh + 360, dh))
    dh = np.where(c1p * c2p == 0, 0.0, dh)
    dhh = 2 * np.sqrt(c1p * c2p) * np.sin(np.radians(dh) / 2)
    l_mean, cp_mean = (l1 + l2) / 2, (c1p + c2p) / 2
    h_sum = h1p + h2p
    h_mean = np.where(np.abs(h1p - h2p) <= 180, h_sum / 2, np.where(h_sum < 360, (h_sum + 360) / 2, (h_sum - 360) / 2))
    h_mean = np.where(c1p * c2p == 0, h_sum, h_mean)
    t = (1 - 0.17 * np.cos(np.radians(h_mean - 30)) + 0.24 * np.cos(np.radians(2 * h_mean))
         + 0.32 * np.cos(np.radians(3 * h_mean + 6)) - 0.20 * np.cos(np.radians(4 * h_mean - 63)))
    d_theta = 30 * np.exp(-(((h_mean - 275) / 25) ** 2))
    r_c = 2 * np.sqrt(cp_mean ** 7 / (cp_mean ** 7 + 25.0 ** 7))
    s_l = 1 + 0.015 * (l_mean - 50) ** 2 / np.sqrt(20 + (l_mean - 50) ** 2)
    s_c = 1 + 0.045 * cp_mean
    s_h = 1 + 0.015 * cp_mean * t
    r_t = -np.sin(np.radians(2 * d_theta)) * r_c
    return np.sqrt((dl / s_l) ** 2 + (dc / s_c) ** 2 + (dhh / s_h) ** 2 + r_t * (dc / s_c) * (dhh / s_h))


def colour_difference(reference_linear: np.ndarray, decoded_linear: np.ndarray) -> tuple[float, float]:
    """(mean, 99th percentile) CIEDE2000 of two linear-light images' RGB, texel by texel."""
    de = ciede2000(linear_to_lab(reference_linear), linear_to_lab(decoded_linear)).reshape(-1)
    return float(de.mean()), float(np.percentile(de, 99))
