"""bufferViews compressed with meshoptimizer's codecs (EXT_meshopt_compression, KHR_meshopt_compression),
decoded in numpy.

Why by hand: no meshopt decoder installs from wheels on every platform and Python this project supports
(`meshopt` needs Python 3.12, `almeshopt` has no macOS wheels, `meshoptimizer` is source only), and the
two extensions specify the bitstream completely. The attribute codec is walked once in Python to find where
each group of 16 deltas starts (the sentinel bytes make the offsets sequential), then every group is
unpacked at once; the index codecs carry a FIFO from triangle to triangle and step in Python.

Every read is bounded by the compressed view's length and the decoded size by the parent bufferView's, so
a hostile stream stops with MeshoptError (the reader names the view) rather than reading or writing past
either; a stream that leaves bytes unread, or reads a FIFO entry never written, is refused as the KHR
extension asks.
"""

from __future__ import annotations

from array import array

import numpy as np

from ...errors import CrowdError

EXTENSIONS = ("EXT_meshopt_compression", "KHR_meshopt_compression")
MODES = ("ATTRIBUTES", "TRIANGLES", "INDICES")
FILTERS = ("NONE", "OCTAHEDRAL", "QUATERNION", "EXPONENTIAL", "COLOR")


class MeshoptError(CrowdError, ValueError):
    """A compressed view its extension does not allow, or whose stream does not decode. One line (the
    reader turns it into a GltfImportError naming the file and the bufferView)."""


def check_layout(ext: str, count: int, stride: int, mode: str, filt: str, parent_length: int) -> None:
    """The extension's validity rules for one view, before anything is decoded."""
    if mode not in MODES:
        raise MeshoptError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
    if filt not in FILTERS or (filt == "COLOR" and ext != EXTENSIONS[1]):
        allowed = FILTERS if ext == EXTENSIONS[1] else FILTERS[:-1]
        raise MeshoptError(f"filter must be one of {', '.join(allowed)}, got {filt!r}")
    if mode == "ATTRIBUTES":
        if stride % 4 or not 4 <= stride <= 256:
            raise MeshoptError(f"byteStride {stride} of ATTRIBUTES must be a multiple of 4 from 4 to 256")
    else:
        if stride not in (2, 4):
            raise MeshoptError(f"byteStride {stride} of {mode} must be 2 or 4")
        if filt != "NONE":
            raise MeshoptError(f"{mode} takes no filter, got {filt}")
        if mode == "TRIANGLES" and count % 3:
            raise MeshoptError(f"count {count} of TRIANGLES is not a multiple of 3")
    needs = {"OCTAHEDRAL": (4, 8), "QUATERNION": (8,), "COLOR": (4, 8)}.get(filt)
    if needs and stride not in needs:
        raise MeshoptError(f"filter {filt} needs a byteStride of {' or '.join(map(str, needs))}, got {stride}")
    if count * stride != parent_length:
        raise MeshoptError(f"count {count} times byteStride {stride} is not the bufferView's byteLength {parent_length}")


def decode(src: bytes, count: int, stride: int, mode: str, filt: str, khr: bool) -> bytes:
    """The view's `count * stride` bytes from its compressed stream `src`."""
    if mode == "ATTRIBUTES":
        out = decode_attributes(src, count, stride, khr)
        if filt != "NONE":
            out = _FILTER[filt](out, stride)
        return out.tobytes()
    indices = decode_triangles(src, count) if mode == "TRIANGLES" else decode_sequence(src, count)
    return indices.astype("<u2" if stride == 2 else "<u4").tobytes()


# -- mode 0, attributes

# Bits per delta for each group's 2-bit header: version 0, then version 1's control modes 0 and 1.
_WIDTHS = {0: (0, 2, 4, 8), (1, 0): (0, 1, 2, 4), (1, 1): (1, 2, 4, 8)}
# Each header byte as its four groups' bit widths, and each byte's count of all-ones fields per width.
_HEADERS = {key: [tuple(w[(b >> 2 * g) & 3] for g in range(4)) for b in range(256)] for key, w in _WIDTHS.items()}
_CHUNK = 1 << 16  # groups unpacked at once
_SENTINELS = {bits: bytes(sum(((b >> s) & ((1 << bits) - 1)) == (1 << bits) - 1 for s in range(0, 8, bits)) for b in range(256))
              for bits in (1, 2, 4)}


def decode_attributes(src: bytes, count: int, stride: int, khr: bool) -> np.ndarray:
    """(count, stride) uint8: the elements the attribute codec stored."""
    size = len(src)
    if size < 1 or src[0] >> 4 != 0xA:
        raise MeshoptError(f"is not an ATTRIBUTES stream (header {src[0]:#04x})" if size else "is empty")
    version = src[0] & 0xF
    if version > 1 or (version == 1 and not khr):
        raise MeshoptError(f"uses version {version} of the attribute codec, which "
                           + ("only KHR_meshopt_compression allows" if version == 1 else "no meshopt extension defines"))
    channels = stride // 4
    tail = stride + (channels if version else 0)
    end = size - max(tail, 24 if version else 32)
    if end < 1:
        raise MeshoptError(f"holds {size} bytes, too few for its tail of {max(tail, 24 if version else 32)}")
    baseline = np.frombuffer(src, np.uint8, stride, size - tail)
    modes = np.frombuffer(src, np.uint8, channels, size - channels) if version else np.zeros(channels, np.uint8)
    bad = (modes & 0xF > 2) | ((modes & 0xF < 2) & (modes >> 4 != 0))
    if bad.any():
        k = int(np.argmax(bad))
        raise MeshoptError(f"channel {k} has mode byte {int(modes[k]):#04x}, which the codec does not define")

    block_max = min((8192 // stride) & ~15, 256)
    groups = (count + 15) // 16
    deltas = np.zeros((groups * 16, stride), np.uint8)  # zigzag-coded, or XOR words' bytes
    # The walk: where each group's deltas start. Sentinel counts per byte come from translate tables
    # (made for the widths the stream uses) so that the one sequential step per group stays a few C calls.
    sentinels = _Sentinels(src)
    offsets = {bits: array("i") for bits in (1, 2, 4, 8)}  # (a stream is under 2 GiB: the file budget)
    cells = {bits: array("i") for bits in (1, 2, 4, 8)}  # (element // 16) * stride + byte
    pos, row = 1, 0
    while row < count:
        block_rows = min(count - row, block_max)
        block_groups = (block_rows + 15) // 16
        control = 0
        if version:
            if pos + channels > end:
                raise MeshoptError(f"runs out of data in the block at element {row}")
            control = int.from_bytes(src[pos:pos + channels], "little")
            pos += channels
        for k in range(stride):
            ctrl = (control >> 2 * k) & 3
            if ctrl == 2:
                continue
            if ctrl == 3:
                n = block_rows  # literal bytes: one per element, not padded to the group
                if pos + n > end:
                    raise MeshoptError(f"runs out of data at byte {k} of the block at element {row}")
                deltas[row:row + n, k] = np.frombuffer(src, np.uint8, n, pos)
                pos += n
                continue
            table = _HEADERS[(1, ctrl) if version else 0]
            header = src[pos:pos + (block_groups + 3) // 4]
            pos += (block_groups + 3) // 4
            cell = (row // 16) * stride + k
            g = 0
            for head in header:
                for bits in table[head]:
                    if g == block_groups or pos > end:
                        break
                    if bits:
                        offsets[bits].append(pos)
                        cells[bits].append(cell + g * stride)
                        if bits == 8:
                            pos += 16
                        else:
                            packed = 2 * bits
                            pos += packed + sum(sentinels[bits][pos:pos + packed])
                    g += 1
            if pos > end:
                raise MeshoptError(f"runs out of data at byte {k} of the block at element {row}")
        row += block_groups * 16
    if pos != end:
        raise MeshoptError(f"leaves {end - pos} bytes unread before its tail")

    del sentinels
    data = np.frombuffer(src, np.uint8)
    flat = deltas.reshape(-1)
    lane = np.arange(16)
    for bits in offsets:
        # In chunks of groups, so that the index arrays (16 int64 a group) stay small beside the data.
        for start in range(0, len(offsets[bits]), _CHUNK):
            offset = np.frombuffer(offsets[bits], np.int32)[start:start + _CHUNK].astype(np.int64)[:, None]
            cell = np.frombuffer(cells[bits], np.int32)[start:start + _CHUNK].astype(np.int64)
            at = ((cell // stride) * 16 * stride + cell % stride)[:, None] + lane * stride  # the group's 16 bytes in `deltas`
            if bits == 8:
                flat[at] = data[offset + lane]
                continue
            packed = 2 * bits
            raw = data[offset + np.arange(packed)]
            # 2- and 4-bit fields run from the high bits of each byte down, 1-bit fields from the low bit up.
            shifts = np.arange(0, 8, bits) if bits == 1 else np.arange(8 - bits, -1, -bits)
            fields = ((raw[:, :, None] >> shifts.astype(np.uint8)) & ((1 << bits) - 1)).reshape(len(cell), 16)
            sentinel = fields == (1 << bits) - 1
            extra = offset + packed + np.cumsum(sentinel, axis=1) - 1
            flat[at] = np.where(sentinel, data[np.where(sentinel, extra, 0)], fields)

    return _undelta(deltas[:count], baseline, modes, stride)


class _Sentinels(dict):
    """bits -> the stream's bytes, each replaced by its count of all-ones `bits`-wide fields; made on first use."""

    def __init__(self, src: bytes):
        super().__init__()
        self.src = src

    def __missing__(self, bits: int) -> bytes:
        self[bits] = table = self.src.translate(_SENTINELS[bits])
        return table


def _undelta(deltas: np.ndarray, baseline: np.ndarray, modes: np.ndarray, stride: int) -> np.ndarray:
    """Each element from the one before it (the first from the baseline), channel by channel."""
    count = len(deltas)
    out = np.empty((count, stride), np.uint8)
    for c, mode in enumerate(modes):
        cols = slice(4 * c, 4 * c + 4)
        kind, rotate = int(mode) & 0xF, int(mode) >> 4
        if kind == 0:
            z = deltas[:, cols]
            d = (z >> 1) ^ (0 - (z & 1)).astype(np.uint8)
            out[:, cols] = baseline[cols] + np.cumsum(d, axis=0, dtype=np.uint8)
        elif kind == 1:
            z = np.ascontiguousarray(deltas[:, cols]).view("<u2")
            d = (z >> 1) ^ (0 - (z & 1)).astype(np.uint16)
            base = baseline[cols].copy().view("<u2")
            out[:, cols] = (base + np.cumsum(d, axis=0, dtype=np.uint16)).astype("<u2").view(np.uint8).reshape(count, 4)
        else:
            z = np.ascontiguousarray(deltas[:, cols]).view("<u4")[:, 0]
            if rotate:
                z = (z >> np.uint32(rotate)) | (z << np.uint32(32 - rotate))
            words = np.bitwise_xor.accumulate(np.concatenate([baseline[cols].copy().view("<u4"), z]))[1:]
            out[:, cols] = words.astype("<u4").view(np.uint8).reshape(count, 4)
    return out


# -- filters, applied to the decoded elements


def _round(x: np.ndarray) -> np.ndarray:
    """Half away from zero, as the extensions specify."""
    return np.trunc(x + np.copysign(0.5, x))


def _octahedral(elems: np.ndarray, stride: int) -> np.ndarray:
    # The spec's decode with its division by the stored 1.0 left out: the renormalisation cancels it.
    v = np.ascontiguousarray(elems).view("<i1" if stride == 4 else "<i2").astype(np.float64)
    top = 127.0 if stride == 4 else 32767.0
    x, y = v[:, 0], v[:, 1]
    z = v[:, 2] - np.abs(x) - np.abs(y)
    t = np.minimum(z, 0.0)
    x = x - np.copysign(t, x)
    y = y - np.copysign(t, y)
    length = np.sqrt(x * x + y * y + z * z)
    scale = top / np.where(length > 0, length, 1.0)
    out = np.stack([_round(x * scale), _round(y * scale), _round(z * scale), v[:, 3]], axis=1)
    return out.astype("<i1" if stride == 4 else "<i2").view(np.uint8)


def _quaternion(elems: np.ndarray, stride: int) -> np.ndarray:
    v = np.ascontiguousarray(elems).view("<i2")
    xyz = v[:, :3] / (v[:, 3:] | 3).astype(np.float64) * np.sqrt(0.5)
    w = np.sqrt(np.maximum(0.0, 1.0 - (xyz * xyz).sum(axis=1)))
    parts = _round(np.concatenate([w[:, None], xyz], axis=1) * 32767.0).astype(np.int16)
    first = (v[:, 3] & 3).astype(np.int64)
    out = np.empty_like(parts)
    rows = np.arange(len(v))[:, None]
    out[rows, (first[:, None] + np.arange(4)) % 4] = parts  # the omitted largest component sits at `first`
    return out.astype("<i2").view(np.uint8)


def _exponential(elems: np.ndarray, stride: int) -> np.ndarray:
    v = np.ascontiguousarray(elems).view("<i4")
    e = v >> 24
    m = (v << 8) >> 8
    with np.errstate(over="ignore"):  # exponents past the valid +-100 give infinity, which the reader's value checks refuse
        return np.ldexp(m.astype(np.float32), e).astype("<f4").view(np.uint8)


def _color(elems: np.ndarray, stride: int) -> np.ndarray:
    signed = np.ascontiguousarray(elems).view("<i1" if stride == 4 else "<i2").astype(np.int32)
    unsigned = np.ascontiguousarray(elems).view("<u1" if stride == 4 else "<u2").astype(np.int32)
    y, co, cg, alpha = unsigned[:, 0], signed[:, 1], signed[:, 2], unsigned[:, 3]
    top_bit = np.where(alpha > 0, np.floor(np.log2(np.maximum(alpha, 1))).astype(np.int32), 0)
    a_scale = (1 << (top_bit + 1)) - 1
    a = alpha & (a_scale >> 1)
    a = (a << 1) | (a & 1)
    ss = (255.0 if stride == 4 else 65535.0) / a_scale
    rgba = np.stack([y + co - cg, y + cg, y - co - cg, a], axis=1) * ss[:, None]
    limit = 255 if stride == 4 else 65535
    return np.clip(_round(rgba), 0, limit).astype("<u1" if stride == 4 else "<u2").view(np.uint8)


_FILTER = {"OCTAHEDRAL": _octahedral, "QUATERNION": _quaternion, "EXPONENTIAL": _exponential, "COLOR": _color}


# -- modes 1 and 2, indices


def _varint(src: bytes, pos: int, end: int) -> tuple[int, int]:
    value = shift = 0
    for _ in range(5):
        if pos >= end:
            raise MeshoptError("runs out of data in an index")
        byte = src[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value & 0xFFFF_FFFF, pos
        shift += 7
    raise MeshoptError(f"has an index longer than 5 bytes at byte {pos - 5}")


def _index_stream(src: bytes, header: int, mode: str, tail: int, least: int, what: str) -> int:
    """Where the tail of an index stream starts, once its header byte and its length (at least `least`
    bytes between the header and a `tail`-byte tail) are checked."""
    if not src or src[0] != header:
        raise MeshoptError(f"is not {'an' if mode[0] in 'AEIOU' else 'a'} {mode} stream (header {src[0]:#04x}; {header:#04x} expected)"
                           if src else "is empty")
    end = len(src) - tail
    if end < 1 + least:
        raise MeshoptError(f"holds {len(src)} bytes, too few for {least} {what}")
    return end


def decode_triangles(src: bytes, count: int) -> np.ndarray:
    """Mode 1: a triangle list, each triangle a code byte that reuses recent edges and vertices."""
    triangles = count // 3
    end = _index_stream(src, 0xE1, "TRIANGLES", 16, triangles, "triangle codes and the 16-byte table")
    aux = src[end:]
    if aux[14] or aux[15] or any(b >> 4 == 0xF or b & 0xF == 0xF for b in aux):
        raise MeshoptError("has a code table that the codec does not allow")
    edge_a, edge_b, vert = [0] * 16, [0] * 16, [0] * 16
    edges = verts = 0  # entries written so far: a FIFO slot never written must not be read
    nxt = last = 0
    pos = 1 + triangles
    out = [0] * (3 * triangles)
    mask = 0xFFFF_FFFF

    def index(pos: int) -> tuple[int, int]:
        nonlocal last
        if pos < end and src[pos] < 0x80:  # one byte, the common case
            v, pos = src[pos], pos + 1
        else:
            v, pos = _varint(src, pos, end)
        last = (last + ((~(v >> 1)) if v & 1 else (v >> 1))) & mask
        return last, pos

    def recent(i: int) -> int:
        if i >= min(verts, 16):
            raise MeshoptError(f"reads vertex FIFO entry {i} before it was written, at triangle {t}")
        return vert[(verts - 1 - i) & 15]

    for t in range(triangles):
        code = src[1 + t]
        hi, lo = code >> 4, code & 0xF
        if hi < 0xF:
            if hi >= min(edges, 16):
                raise MeshoptError(f"reads edge FIFO entry {hi} before it was written, at triangle {t}")
            slot = (edges - 1 - hi) & 15
            a, b = edge_a[slot], edge_b[slot]
            push = True
            if lo == 0:
                c = nxt
                nxt = (nxt + 1) & mask
            elif lo < 0xD:
                c = recent(lo)
                push = False
            elif lo < 0xF:
                c = last = (last + (1 if lo == 0xE else -1)) & mask
            else:
                c, pos = index(pos)
            for ea, eb in ((c, b), (a, c)):
                edge_a[edges & 15], edge_b[edges & 15] = ea, eb
                edges += 1
            if push:
                vert[verts & 15] = c
                verts += 1
        else:
            if lo < 0xE:
                z, w = aux[lo] >> 4, aux[lo] & 0xF
                explicit = False
            else:
                if pos >= end:
                    raise MeshoptError(f"runs out of data at triangle {t}")
                z, w = src[pos] >> 4, src[pos] & 0xF
                pos += 1
                if z == 0 and w == 0:
                    nxt = 0
                explicit = lo == 0xF
            if explicit:
                a, pos = index(pos)
            else:
                a = nxt
                nxt = (nxt + 1) & mask
            corners = [a]
            fresh = [True]
            for sel in (z, w):
                if sel == 0:
                    corners.append(nxt)
                    nxt = (nxt + 1) & mask
                    fresh.append(True)
                elif sel < 0xF:
                    corners.append(recent(sel - 1))
                    fresh.append(False)
                else:
                    v, pos = index(pos)
                    corners.append(v)
                    fresh.append(True)
            a, b, c = corners
            for ea, eb in ((b, a), (c, b), (a, c)):
                edge_a[edges & 15], edge_b[edges & 15] = ea, eb
                edges += 1
            for v, new in zip(corners, fresh):
                if new:
                    vert[verts & 15] = v
                    verts += 1
        out[3 * t:3 * t + 3] = a, b, c
    if pos != end:
        raise MeshoptError(f"leaves {end - pos} bytes of triangle data unread")
    return np.array(out, np.uint32)


def decode_sequence(src: bytes, count: int) -> np.ndarray:
    """Mode 2: indices as deltas from one of two running baselines. Nothing carries from index to index
    but the baselines' sums, so the varints and the sums are worked out at once."""
    end = _index_stream(src, 0xD1, "INDICES", 4, count, "indices and the 4-byte tail")
    body = np.frombuffer(src, np.uint8, end - 1, 1)
    last = np.flatnonzero(body < 0x80)  # each varint's last byte
    if len(last) < count:
        raise MeshoptError(f"runs out of data after {len(last)} of its {count} indices")
    used = int(last[count - 1]) + 1
    if used != len(body):
        raise MeshoptError(f"leaves {len(body) - used} bytes of index data unread")
    first = np.concatenate([[0], last[:count - 1] + 1])
    lengths = last[:count] - first + 1
    if lengths.max() > 5:
        k = int(np.argmax(lengths > 5))
        raise MeshoptError(f"has an index longer than 5 bytes at byte {int(first[k]) + 1}")
    place = np.arange(used) - np.repeat(first, lengths)  # each byte's place in its varint
    v = np.add.reduceat((body.astype(np.uint64) & 0x7F) << (7 * place).astype(np.uint64), first) & 0xFFFF_FFFF
    delta = np.where(v & 2, ~(v >> 2), v >> 2) & 0xFFFF_FFFF
    out = np.empty(count, np.uint32)
    for baseline in (0, 1):
        mine = np.flatnonzero((v & 1) == baseline)
        out[mine] = np.cumsum(delta[mine]) & 0xFFFF_FFFF
    return out
