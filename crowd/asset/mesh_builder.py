"""The generator's mesh toolkit: generalised cylinders ("tubes") along joint chains, weighted by arc
length, gathered into skinned or rigid meshes whose floats are quantised so that the output is
deterministic; and the value noise the built-ins colour and tear with."""

from __future__ import annotations

import math

import numpy as np

from .model import RigidMesh, SkinnedMesh, vertex_normals

# Rings and segments divided by this per LOD: ~1, 1/4, 1/16 and 1/40 of the triangles. LOD3 is for the
# far crowd (26 px tall at its default 90 m on the demo's 45-degree camera at 1080p), where the GPU's
# triangle rate, not its shading, bounds the draw (docs/BENCHMARKS.md, "The coarse LOD").
LOD_DIVISORS = (1, 2, 4, 8)


class _MeshBuilder:
    def __init__(self):
        self.pos: list[np.ndarray] = []
        self.jnt: list[np.ndarray] = []
        self.wgt: list[np.ndarray] = []
        self.col: list[np.ndarray] = []
        self.idx: list[np.ndarray] = []
        self.count = 0

    def add(self, pos, jnt, wgt, col, tris):
        self.pos.append(pos)
        self.jnt.append(jnt)
        self.wgt.append(wgt)
        self.col.append(col)
        self.idx.append(np.asarray(tris, dtype=np.int64) + self.count)
        self.count += pos.shape[0]

    def build(self, name, piece, lod, base_color, group="") -> SkinnedMesh:
        pos = np.concatenate(self.pos)
        idx = np.concatenate(self.idx).reshape(-1)
        jnt = np.concatenate(self.jnt)
        wgt = np.concatenate(self.wgt)
        col = np.concatenate(self.col)
        pos = _quantise(pos, 1e-6)
        normals = _quantise(vertex_normals(pos, idx), 1e-6)
        jnt, wgt = _top4(jnt, wgt)
        return SkinnedMesh(
            name=name,
            piece=piece,
            lod=lod,
            positions=pos.astype(np.float32),
            normals=normals.astype(np.float32),
            joints=jnt.astype(np.uint16),
            weights=wgt.astype(np.float32),
            indices=idx.astype(np.uint32),
            colors=np.round(np.clip(col, 0.0, 1.0) * 255.0).astype(np.float32) / 255.0,
            base_color=base_color,
            group=group,
        )


def _quantise(a: np.ndarray, step: float) -> np.ndarray:
    """Round to a grid so that last-bit differences between numpy builds cannot change the file."""
    return np.round(np.asarray(a, dtype=np.float64) / step) * step


def _top4(jnt: np.ndarray, wgt: np.ndarray):
    """Keep the 4 largest influences per vertex, quantise them to 1/65535 steps and renormalise exactly."""
    order = np.argsort(-wgt, axis=1, kind="stable")[:, :4]
    j = np.take_along_axis(jnt, order, axis=1)
    w = np.take_along_axis(wgt, order, axis=1)
    w = np.where(w < 1e-3, 0.0, w)
    w = w / w.sum(axis=1, keepdims=True)
    w = _quantise(w, 1.0 / 65535.0)
    w[:, 0] = 1.0 - w[:, 1:].sum(axis=1)  # the residue goes to the heaviest influence
    j = np.where(w > 0.0, j, 0)
    return j, w


def _frames_along(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotation-minimising frames (tangent, normal, binormal) along a polyline."""
    d = np.gradient(points, axis=0)
    t = d / np.linalg.norm(d, axis=1, keepdims=True)
    up = np.array([0.0, 0.0, 1.0]) if abs(t[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    n = np.cross(up, t[0])
    n /= np.linalg.norm(n)
    ns = [n]
    for k in range(1, len(t)):
        v = ns[-1] - t[k] * np.dot(ns[-1], t[k])
        ns.append(v / np.linalg.norm(v))
    n = np.array(ns)
    b = np.cross(t, n)
    return t, n, b


def _chain_weights(s: np.ndarray, breaks: list[float], bones: list[int], blend: list[float], joint_count: int) -> np.ndarray:
    """Dense (N, J) weights along a chain: bone k owns [breaks[k], breaks[k+1]], smoothstep blends around each break."""
    w = np.zeros((s.shape[0], joint_count))
    own = np.zeros((s.shape[0], len(bones)))
    for k in range(len(bones)):
        lo = 1.0 if k == 0 else _smoothstep((s - (breaks[k] - blend[k])) / (2.0 * blend[k]))
        hi = 1.0 if k == len(bones) - 1 else 1.0 - _smoothstep((s - (breaks[k + 1] - blend[k + 1])) / (2.0 * blend[k + 1]))
        own[:, k] = lo * hi
    own /= np.maximum(own.sum(axis=1, keepdims=True), 1e-9)
    for k, b in enumerate(bones):
        w[:, b] += own[:, k]
    return w


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _tube(
    builder: _MeshBuilder,
    spine_pts: np.ndarray,
    radius_x,
    radius_y,
    rings: int,
    segments: int,
    bones: list[int],
    breaks: list[float],
    blend: list[float],
    color_fn,
    joint_count: int,
    cap_start=True,
    cap_end=True,
    displace=None,
    keep_quad=None,
):
    """A closed tube along a polyline. radius_x/radius_y are functions of u in [0, 1] (elliptic sections).
    A coarse LOD's division may ask for fewer than 3 sides, which would have no area: 3 is the floor.
    A polygon inscribed in the section is narrower than it, so a far LOD's limbs thinned and its
    silhouette shrank: tubes of 8 sides or fewer are widened to the section's mean width over every
    view direction (its perimeter / pi: x 1.21 for 3 sides, 1.11 for 4, 1.05 for 6); LOD0's 10 to 24
    sides are as modelled. Widening to the section's area instead (x 1.56 for 3) overshot: LOD2's
    silhouette IoU went down (bench/lod_silhouette.py, docs/BENCHMARKS.md)."""
    rings, segments = max(rings, 1), max(segments, 3)
    if segments <= 8:
        widen = math.pi / (segments * math.sin(math.pi / segments))
        radius_x, radius_y = (lambda f: lambda u: widen * f(u))(radius_x), (lambda f: lambda u: widen * f(u))(radius_y)
    seg_len = np.linalg.norm(np.diff(spine_pts, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg_len)])
    u = np.linspace(0.0, 1.0, rings + 1)
    s = u * arc[-1]
    centre = np.stack([np.interp(s, arc, spine_pts[:, i]) for i in range(3)], axis=1)
    t, n, b = _frames_along(centre)
    ang = np.linspace(0.0, 2.0 * math.pi, segments, endpoint=False)
    rx = np.array([radius_x(x) for x in u])[:, None]
    ry = np.array([radius_y(x) for x in u])[:, None]
    offs = (rx * np.cos(ang))[..., None] * n[:, None, :] + (ry * np.sin(ang))[..., None] * b[:, None, :]
    if displace is not None:
        offs = offs * displace(u[:, None], ang[None, :])[..., None]
    ring_pos = centre[:, None, :] + offs  # (R+1, S, 3)
    pos = ring_pos.reshape(-1, 3)
    w_ring = _chain_weights(u, breaks, bones, blend, joint_count)  # breaks and blends are arc-length fractions
    w = np.repeat(w_ring, segments, axis=0)
    col = color_fn(pos, np.repeat(u, segments))
    tris = []
    for r in range(rings):
        for k in range(segments):
            if keep_quad is not None and not keep_quad(r, k, rings, segments):
                continue
            a = r * segments + k
            bq = r * segments + (k + 1) % segments
            c = (r + 1) * segments + k
            d = (r + 1) * segments + (k + 1) % segments
            tris += [(a, c, bq), (bq, c, d)]
    extra_pos, extra_w, extra_c = [], [], []
    base = pos.shape[0]
    for end, cap in ((0, cap_start), (rings, cap_end)):
        if not cap:
            continue
        tip = centre[end] + t[end] * (-0.35 if end == 0 else 0.35) * float(min(rx[end, 0], ry[end, 0]))
        extra_pos.append(tip)
        extra_w.append(w_ring[end])
        extra_c.append(color_fn(tip[None], np.array([u[end]]))[0])
        ci = base + len(extra_pos) - 1
        for k in range(segments):
            a = end * segments + k
            bq = end * segments + (k + 1) % segments
            tris.append((ci, bq, a) if end == 0 else (ci, a, bq))
    if extra_pos:
        pos = np.concatenate([pos, np.array(extra_pos)])
        w = np.concatenate([w, np.array(extra_w)])
        col = np.concatenate([col, np.array(extra_c)])
    jnt = np.tile(np.arange(joint_count), (pos.shape[0], 1))
    builder.add(pos, jnt, w, col, tris)


def _noise(seed: int, *coords) -> np.ndarray:
    """Cheap deterministic value noise from hashed sines: enough for skin blotches and wounds."""
    acc = 0.0
    for i, c in enumerate(coords):
        acc = acc + np.asarray(c, dtype=np.float64) * (12.9898 + 7.233 * i + seed * 1.618)
    return np.mod(np.sin(acc) * 43758.5453, 1.0)


def _rigid_from_builder(m: _MeshBuilder, name: str, color) -> RigidMesh:
    sk = m.build(name, name, 0, color)
    return RigidMesh(name, sk.positions, sk.normals, sk.indices, sk.colors, color)
