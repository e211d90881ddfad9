"""The built-in zombie, generated entirely by this module: ``python -m crowd.asset.zombie`` writes assets/zombie.glb.

Why generate it rather than ship an artist's file: the project must run with nothing downloaded, and
every vertex, weight and key here is reproducible from code a reader can change. The output is
byte-for-byte deterministic (all floats are quantised before they are packed), so a test can
regenerate the file and compare it with the committed one.

Conventions: metres, +Y up, the character faces +Z, its left side is +X. The rest pose is a T-pose
with every joint's local rotation at identity, so joint axes are world-aligned at rest.

Weapon socket ("weapon_r", joint ``hand_r_socket``): origin at the centre of the closed right fist,
8 cm past the wrist; +Y runs along the held handle towards the weapon's head (out of the thumb side
of the fist), +Z points out of the palm, +X points back towards the wrist. Weapons are modelled with
the handle along +Y; each has a ``*_grip`` node whose frame is placed onto the socket frame.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
from pathlib import Path

import numpy as np

from .. import transforms as tf
from ..resources import ASSET_DIR
from .pose import LocalPose, global_matrices, rest_pose
from .model import Channel, Character, Clip, MorphChannel, Prop, RigidMesh, Skeleton, SkinnedMesh, vertex_normals

ASSET_PATH = ASSET_DIR / "zombie.glb"
SOURCE_FPS = 30  # clips are authored as keys at this rate; the bake resamples them
# Rings and segments divided by this per LOD: ~1, 1/4, 1/16 and 1/40 of the triangles. LOD3 is for the
# far crowd (26 px tall at its default 90 m on the demo's 45-degree camera at 1080p), where the GPU's
# triangle rate, not its shading, bounds the draw (docs/BENCHMARKS.md, "The coarse LOD").
LOD_DIVISORS = (1, 2, 4, 8)

# ------------------------------------------------------------------------------------------------
# Skeleton: (name, parent, rest position in model space)

_JOINTS = [
    ("hips", None, (0.0, 0.98, 0.0)),
    ("spine", "hips", (0.0, 1.10, -0.01)),
    ("chest", "spine", (0.0, 1.28, -0.015)),
    ("neck", "chest", (0.0, 1.50, -0.01)),
    ("head", "neck", (0.0, 1.60, 0.0)),
    ("jaw", "head", (0.0, 1.63, 0.035)),
    ("shoulder_l", "chest", (0.03, 1.44, -0.01)),
    ("upper_arm_l", "shoulder_l", (0.18, 1.44, -0.01)),
    ("forearm_l", "upper_arm_l", (0.46, 1.44, -0.01)),
    ("hand_l", "forearm_l", (0.71, 1.44, -0.01)),
    ("shoulder_r", "chest", (-0.03, 1.44, -0.01)),
    ("upper_arm_r", "shoulder_r", (-0.18, 1.44, -0.01)),
    ("forearm_r", "upper_arm_r", (-0.46, 1.44, -0.01)),
    ("hand_r", "forearm_r", (-0.71, 1.44, -0.01)),
    ("hand_r_socket", "hand_r", (-0.79, 1.435, -0.01)),
    ("thigh_l", "hips", (0.10, 0.93, 0.0)),
    ("shin_l", "thigh_l", (0.10, 0.51, 0.005)),
    ("foot_l", "shin_l", (0.10, 0.09, -0.01)),
    ("toe_l", "foot_l", (0.10, 0.025, 0.125)),
    ("thigh_r", "hips", (-0.10, 0.93, 0.0)),
    ("shin_r", "thigh_r", (-0.10, 0.51, 0.005)),
    ("foot_r", "shin_r", (-0.10, 0.09, -0.01)),
    ("toe_r", "foot_r", (-0.10, 0.025, 0.125)),
]
JOINT_NAMES = tuple(j[0] for j in _JOINTS)
SOCKET_JOINT = "hand_r_socket"
# Socket frame relative to the hand: +Y (handle) -> model +Z, +Z (out of the palm) -> model -Y.
SOCKET_ROTATION = tf.quat_from_axis_angle([1.0, 0.0, 0.0], math.pi / 2)


@dataclasses.dataclass(frozen=True)
class Body:
    """A build of the generator's skeleton (its joints, names and hierarchy always the zombie's): where
    the joints stand at rest, and what the planted-feet clips and the grounding need of its feet. The
    zombie is ``ZOMBIE_BODY``; crowd.asset.brute makes a heavier one."""

    joints: tuple  # (name, parent, rest position in model space), in _JOINTS' order
    stance_ankle_y: float = 0.085  # the ankle joint's height with the foot flat: its lowest sole point (see heel, tip) at y = 0
    toe_from_ankle: tuple = (0.0, -0.065, 0.135)  # the toe joint from the foot joint at rest
    heel: tuple = (0.0, -0.055, -0.06)  # a sole point under the heel, in the foot joint's frame
    tip: tuple = (0.0, -0.02, 0.06)  # a sole point under the toes' tip, in the toe joint's frame
    stance_width: float = 0.11  # the ankles' distance from the midline when standing

    def positions(self) -> np.ndarray:
        return np.array([j[2] for j in self.joints], dtype=np.float64)


ZOMBIE_BODY = Body(tuple(_JOINTS))


def _joint_positions(body: Body = ZOMBIE_BODY) -> np.ndarray:
    return body.positions()


def build_skeleton(body: Body = ZOMBIE_BODY) -> Skeleton:
    names = JOINT_NAMES
    parents = np.array([-1 if p is None else names.index(p) for _, p, _ in body.joints], dtype=np.int32)
    pos = _joint_positions(body)
    local_t = np.array([pos[i] - (pos[p] if p >= 0 else 0.0) for i, p in enumerate(parents)])
    rot = tf.quat_identity((len(names),))
    rot[names.index(SOCKET_JOINT)] = SOCKET_ROTATION
    skel = Skeleton(names, parents, local_t, rot, np.ones((len(names), 3)), np.tile(np.eye(4), (len(names), 1, 1)))

    bind = global_matrices(skel, rest_pose(skel))[0]
    skel.inverse_bind = np.linalg.inv(bind)
    return skel.validate()


# ------------------------------------------------------------------------------------------------
# Mesh building: generalised cylinders ("tubes") along joint chains, weighted by arc length.


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


@dataclasses.dataclass(frozen=True)
class Palette:
    """The vertex colours of a build: skin, trousers, shoes, shirt and blood (linear RGB)."""

    skin: tuple = (0.46, 0.55, 0.40)  # sickly grey-green
    pants: tuple = (0.22, 0.20, 0.24)
    shoes: tuple = (0.12, 0.10, 0.09)
    shirt: tuple = (0.55, 0.50, 0.40)
    blood: tuple = (0.35, 0.05, 0.04)
    eyes: tuple = (0.9, 0.85, 0.55)  # milky
    wounds: float = 0.45  # how much of a skin blotch is blood (0: clean skin)
    ragged: bool = True  # torn trouser hems over bare shins (False: trousers down to the shoes)


ZOMBIE_PALETTE = Palette()
BLOOD = np.array(ZOMBIE_PALETTE.blood)


def _skin_color(pos, u, seed=0, palette: Palette = ZOMBIE_PALETTE):
    blotch = _smoothstep((np.sin(pos[:, 0] * 41.0 + 1.3) * np.sin(pos[:, 1] * 37.0) * np.sin(pos[:, 2] * 53.0 + 0.7) - 0.55) * 4.0)
    c = np.array(palette.skin)[None] * (0.92 + 0.08 * np.sin(pos[:, 1] * 23.0))[:, None]
    c = c * (1.0 - palette.wounds * blotch[:, None]) + np.array(palette.blood)[None] * palette.wounds * blotch[:, None]
    return np.concatenate([c, np.ones((pos.shape[0], 1))], axis=1)


def _leg_color(pos, u, palette: Palette = ZOMBIE_PALETTE):
    skin = _skin_color(pos, u, palette=palette)[:, :3]
    c = np.where((pos[:, 1] > (0.22 if palette.ragged else 0.0))[:, None], np.array(palette.pants)[None], skin)
    if not palette.ragged:
        return np.concatenate([c, np.ones((pos.shape[0], 1))], axis=1)
    torn = (pos[:, 1] > 0.22) & (pos[:, 1] < 0.36)  # ragged trouser hems above bare shins
    ragged = np.sin(np.arctan2(pos[:, 2], pos[:, 0] - np.sign(pos[:, 0]) * 0.1) * 7.0) * 0.05 + 0.29
    c = np.where((torn & (pos[:, 1] < ragged))[:, None], skin, c)
    return np.concatenate([c, np.ones((pos.shape[0], 1))], axis=1)


def _foot_color(pos, u, palette: Palette = ZOMBIE_PALETTE):
    return np.concatenate([np.repeat(np.array(palette.shoes)[None], pos.shape[0], 0), np.ones((pos.shape[0], 1))], axis=1)


def _torso_color(pos, u, palette: Palette = ZOMBIE_PALETTE):
    c = np.where((pos[:, 1] < 1.0)[:, None], np.array(palette.pants)[None], _skin_color(pos, u, palette=palette)[:, :3])
    return np.concatenate([c, np.ones((pos.shape[0], 1))], axis=1)


def _shirt_color(pos, u, palette: Palette = ZOMBIE_PALETTE):
    stain = _smoothstep((np.sin(pos[:, 0] * 17.0) * np.sin(pos[:, 1] * 13.0 + 1.0) - 0.3) * 3.0)
    c = np.array(palette.shirt)[None] * (1.0 - 0.5 * stain[:, None]) + np.array(palette.blood)[None] * 0.5 * stain[:, None]
    return np.concatenate([c, np.ones((pos.shape[0], 1))], axis=1)


def _colors(palette: Palette):
    """The colour functions (skin, leg, foot, torso, shirt) of a palette, as the tubes call them."""
    return (functools.partial(_skin_color, palette=palette), functools.partial(_leg_color, palette=palette),
            functools.partial(_foot_color, palette=palette), functools.partial(_torso_color, palette=palette),
            functools.partial(_shirt_color, palette=palette))


def _build_body(div: int, palette: Palette = ZOMBIE_PALETTE) -> SkinnedMesh:
    _skin_color, _leg_color, _foot_color, _torso_color, _ = _colors(palette)
    jc = len(JOINT_NAMES)
    J = JOINT_NAMES.index
    m = _MeshBuilder()

    # Torso: pelvis to the base of the neck, elliptic, thin at the waist, ribs showing.
    pts = np.array([[0.0, 0.84, 0.0], [0.0, 0.98, 0.0], [0.0, 1.10, -0.01], [0.0, 1.28, -0.015], [0.0, 1.49, -0.02]])
    width = lambda u: float(np.interp(u, [0, 0.2, 0.45, 0.7, 0.9, 1.0], [0.13, 0.165, 0.13, 0.165, 0.175, 0.09]))
    depth = lambda u: float(np.interp(u, [0, 0.2, 0.45, 0.7, 0.9, 1.0], [0.10, 0.11, 0.09, 0.11, 0.10, 0.07]))

    def ribs(u, a):
        front = np.clip(np.sin(a), 0.0, 1.0) ** 2  # the normal axis is +X, binormal is +Z: front is sin > 0
        band = (u > 0.5) & (u < 0.85)
        return 1.0 + np.where(band, 0.035 * front * np.sin(u * 70.0), 0.0) + 0.02 * (_noise(1, u * 31.0, a * 5.0) - 0.5)

    _tube(m, pts, width, depth, 20 // div, 24 // div, [J("hips"), J("spine"), J("chest")],
          [0.0, 0.14 / 0.65, 0.44 / 0.65, 1.0], [0.0, 0.06, 0.07], _torso_color, jc, displace=ribs)

    # Neck.
    pts = np.array([[0.0, 1.45, -0.015], [0.0, 1.55, -0.005], [0.0, 1.64, 0.0]])
    # Neck and feet keep 2 rings of 4 sides down to LOD2. LOD3 (26 px tall, where the GPU's triangle
    # rate bounds the crowd) has neck and feet of one ring of 3 sides and legs of 2 rings (hip, knee,
    # ankle). Leaving its feet out saved 24 more triangles and cost 0.02 of its silhouette IoU
    # (0.72 -> 0.70 at 90 m, the shoes stick out 3 px from the side): they stay.
    small = (max(8 // div, 2), max(12 // div, 4)) if div <= 4 else (1, 3)
    _tube(m, pts, lambda u: 0.052, lambda u: 0.05, *small, [J("chest"), J("neck"), J("head")],
          [0.0, 0.05 / 0.19, 0.15 / 0.19, 1.0], [0.0, 0.15, 0.15], _skin_color, jc, cap_start=False, cap_end=False)

    for side, sx in (("l", 1.0), ("r", -1.0)):
        # Arm: from inside the shoulder to the fingertips. Gaunt: thin upper arm, knobbly elbow.
        a = np.array([[0.10 * sx, 1.445, -0.01], [0.18 * sx, 1.44, -0.01], [0.46 * sx, 1.44, -0.01], [0.71 * sx, 1.44, -0.01], [0.89 * sx, 1.43, -0.005]])
        length = float(np.sum(np.linalg.norm(np.diff(a, axis=0), axis=1)))
        brk = np.array([0.10, 0.18, 0.46, 0.71, 0.89]) - 0.10
        r_arm = lambda u: float(np.interp(u, [0, 0.1, 0.3, 0.45, 0.47, 0.55, 0.75, 0.78, 0.86, 1.0], [0.062, 0.055, 0.042, 0.036, 0.038, 0.04, 0.028, 0.03, 0.04, 0.014]))
        r_arm_v = lambda u: float(np.interp(u, [0, 0.1, 0.3, 0.45, 0.55, 0.75, 0.78, 0.86, 1.0], [0.06, 0.05, 0.04, 0.035, 0.036, 0.026, 0.018, 0.016, 0.008]))
        _tube(m, a, r_arm_v, r_arm, 22 // div, 12 // div,
              [J(f"shoulder_{side}"), J(f"upper_arm_{side}"), J(f"forearm_{side}"), J(f"hand_{side}")],
              list(brk / length), [0.0, 0.05 / length, 0.07 / length, 0.04 / length], _skin_color, jc, cap_start=False)
        # Leg: hip to ankle.
        lg = np.array([[0.10 * sx, 0.99, 0.0], [0.10 * sx, 0.93, 0.0], [0.10 * sx, 0.51, 0.005], [0.10 * sx, 0.07, -0.01]])
        r_leg = lambda u: float(np.interp(u, [0, 0.1, 0.45, 0.5, 0.55, 0.7, 0.95, 1.0], [0.08, 0.078, 0.052, 0.05, 0.052, 0.05, 0.035, 0.035]))
        _tube(m, lg, r_leg, r_leg, 24 // div if div <= 4 else 2, 12 // div, [J("hips"), J(f"thigh_{side}"), J(f"shin_{side}")],
              [0.0, 0.06 / 0.92, 0.48 / 0.92, 1.0], [0.0, 0.06 / 0.92, 0.1 / 0.92], _leg_color, jc, cap_start=False, cap_end=False)
        # Foot: heel to toe, a flattened tube (a worn shoe).
        ft = np.array([[0.10 * sx, 0.055, -0.065], [0.10 * sx, 0.05, 0.02], [0.10 * sx, 0.035, 0.125], [0.10 * sx, 0.03, 0.19]])
        r_fw = lambda u: float(np.interp(u, [0, 0.15, 0.6, 1.0], [0.035, 0.045, 0.05, 0.03]))
        r_fh = lambda u: float(np.interp(u, [0, 0.15, 0.6, 1.0], [0.035, 0.045, 0.03, 0.02]))
        _tube(m, ft, r_fw, r_fh, *small, [J(f"foot_{side}"), J(f"toe_{side}")],
              [0.0, 0.19 / 0.256, 1.0], [0.0, 0.03 / 0.256], _foot_color, jc)
    return m.build("zombie_body", "body", 0, (1.0, 1.0, 1.0, 1.0))


def _build_head(div: int, variant: str, palette: Palette = ZOMBIE_PALETTE) -> SkinnedMesh:
    _skin_color = _colors(palette)[0]
    BLOOD = np.array(palette.blood)
    jc = len(JOINT_NAMES)
    J = JOINT_NAMES.index
    m = _MeshBuilder()
    rings, segs = max(18 // div, 3), max(20 // div, 4)  # at least two latitude rows of four: not a flat sliver
    # A deformed sphere; u runs from the chin (0) to the crown (1).
    lat = np.linspace(-math.pi / 2, math.pi / 2, rings + 1)[1:-1]
    lon = np.linspace(0.0, 2.0 * math.pi, segs, endpoint=False)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    x = np.cos(la) * np.sin(lo)
    y = np.sin(la)
    z = np.cos(la) * np.cos(lo)
    if variant == "head_a":
        rx, ry, rz, cy = 0.085, 0.115, 0.10, 1.71
        sock = 0.03  # deep eye sockets
    else:
        rx, ry, rz, cy = 0.09, 0.13, 0.095, 1.72
        sock = 0.02
    r = np.ones_like(x)
    # Brow ridge, sunken eyes, a nose bump, a jutting jaw, hollow cheeks.
    for ex in (-0.35, 0.35):
        r -= sock / 0.1 * np.exp(-(((x - ex) / 0.18) ** 2 + ((y - 0.12) / 0.13) ** 2)) * (z > 0)
    r += 0.10 * np.exp(-((x / 0.12) ** 2 + ((y - 0.3) / 0.08) ** 2)) * (z > 0)
    r += 0.12 * np.exp(-((x / 0.1) ** 2 + ((y + 0.05) / 0.12) ** 2)) * (z > 0)
    r -= 0.08 * np.exp(-(((np.abs(x) - 0.6) / 0.2) ** 2 + ((y + 0.25) / 0.2) ** 2)) * (z > 0)
    r += 0.06 * np.exp(-((x / 0.5) ** 2 + ((y + 0.65) / 0.2) ** 2)) * (z > -0.2)
    if variant == "head_b":
        # A cracked, lopsided skull with a bulge on one side.
        r += 0.12 * np.exp(-(((x - 0.6) / 0.35) ** 2 + ((y - 0.55) / 0.35) ** 2))
        r -= 0.05 * np.exp(-(((x + 0.5) / 0.2) ** 2 + ((y - 0.6) / 0.4) ** 2))
    r += 0.03 * (_noise(3 if variant == "head_a" else 4, la * 7.0, lo * 3.0) - 0.5)
    pos = np.stack([x * rx * r, cy + y * ry * r, 0.005 + z * rz * r], axis=-1).reshape(-1, 3)
    bottom = np.array([[0.0, cy - ry * 1.02, 0.005]])
    top = np.array([[0.0, cy + ry * (1.1 if variant == "head_b" else 1.0), 0.005]])
    pos = np.concatenate([pos, bottom, top])
    # Weights: the lower front (jaw) follows the jaw joint, the lowest ring blends into the neck.
    jaw = _smoothstep((-(pos[:, 1] - (cy - 0.035)) / 0.04)) * _smoothstep((pos[:, 2] - 0.0) / 0.04)
    neck = _smoothstep((-(pos[:, 1] - (cy - 0.095)) / 0.03)) * (1.0 - jaw)
    w = np.zeros((pos.shape[0], jc))
    w[:, J("jaw")] = jaw * (1.0 - neck)
    w[:, J("neck")] = neck
    w[:, J("head")] = 1.0 - w[:, J("jaw")] - neck
    col = _skin_color(pos, None)
    eye = (np.abs(np.abs(pos[:, 0]) - 0.03) < 0.018) & (np.abs(pos[:, 1] - (cy + 0.015)) < 0.014) & (pos[:, 2] > 0.05)
    col[eye, :3] = np.array(palette.eyes)
    mouth = (np.abs(pos[:, 0]) < 0.035) & (np.abs(pos[:, 1] - (cy - 0.05)) < 0.008) & (pos[:, 2] > 0.05)
    col[mouth, :3] = np.array([0.15, 0.03, 0.03])
    if variant == "head_b":
        crack = (np.abs(pos[:, 0] - 0.04 - 0.02 * np.sin(pos[:, 1] * 90.0)) < 0.012) & (pos[:, 1] > cy + 0.05)
        col[crack, :3] = BLOOD * 0.8
    nr, ns = rings - 1, segs
    tris = []
    for i in range(nr - 1):
        for k in range(ns):
            a, b = i * ns + k, i * ns + (k + 1) % ns
            c, d = (i + 1) * ns + k, (i + 1) * ns + (k + 1) % ns
            tris += [(a, b, c), (b, d, c)]
    bi, ti = nr * ns, nr * ns + 1
    for k in range(ns):
        tris.append((bi, (k + 1) % ns, k))
        tris.append((ti, (nr - 1) * ns + k, (nr - 1) * ns + (k + 1) % ns))
    m.add(pos, np.tile(np.arange(jc), (pos.shape[0], 1)), w, col, tris)
    return m.build(f"zombie_{variant}", variant, 0, (1.0, 1.0, 1.0, 1.0), group="head")


def _build_shirt(div: int, palette: Palette = ZOMBIE_PALETTE) -> SkinnedMesh:
    """A torn shirt: a loose tube over the torso with a ragged hem and holes, plus ripped short sleeves."""
    _shirt_color = _colors(palette)[4]
    jc = len(JOINT_NAMES)
    J = JOINT_NAMES.index
    m = _MeshBuilder()
    pts = np.array([[0.0, 0.97, 0.0], [0.0, 1.10, -0.01], [0.0, 1.28, -0.015], [0.0, 1.50, -0.02]])
    width = lambda u: float(np.interp(u, [0, 0.3, 0.6, 0.85, 1.0], [0.185, 0.16, 0.185, 0.195, 0.11]))
    depth = lambda u: float(np.interp(u, [0, 0.3, 0.6, 0.85, 1.0], [0.125, 0.115, 0.13, 0.12, 0.085]))
    rings, segs = 14 // div, 24 // div

    def keep(r, k, rings_, segs_):
        if r == 0:
            return bool(_noise(7, k * 1.0) > 0.35)  # torn hem
        return not (r in (rings_ // 2, rings_ // 2 + 1) and _noise(8, k * 1.0, r * 1.0) > 0.8)  # holes

    _tube(m, pts, width, depth, rings, segs, [J("hips"), J("spine"), J("chest")], [0.0, 0.13 / 0.53, 0.31 / 0.53, 1.0],
          [0.0, 0.06, 0.07], _shirt_color, jc, cap_start=False, cap_end=False, keep_quad=keep)
    for side, sx in (("l", 1.0), ("r", -1.0)):
        a = np.array([[0.12 * sx, 1.445, -0.01], [0.18 * sx, 1.44, -0.01], [0.30 * sx, 1.44, -0.01]])
        _tube(m, a, lambda u: 0.072 - 0.02 * u, lambda u: 0.068 - 0.02 * u, max(4 // div, 1), max(12 // div, 4),
              [J(f"shoulder_{side}"), J(f"upper_arm_{side}")], [0.0, 0.06 / 0.18, 1.0], [0.0, 0.04 / 0.18], _shirt_color,
              jc, cap_start=False, cap_end=False)
    return m.build("zombie_shirt_torn", "shirt_torn", 0, (1.0, 1.0, 1.0, 1.0))


def _build_shadow_proxy(palette: Palette = ZOMBIE_PALETTE) -> SkinnedMesh:
    """LOD4, for shadows only: a four-sided column from the ankles to the crown, skinned to the hips,
    chest and head, 16 triangles. The far shadow cascade has texels of about half a metre (crowd.draw.shadows),
    where this casts the shadow the whole figure would; the colour pass never reaches LOD4 (three LOD
    distances), and an agent at LOD3 casts its shadow one LOD coarser, from this."""
    jc = len(JOINT_NAMES)
    J = JOINT_NAMES.index
    m = _MeshBuilder()
    pts = np.array([[0.0, 0.05, 0.0], [0.0, 0.95, 0.0], [0.0, 1.45, -0.02], [0.0, 1.78, 0.0]])
    width = lambda u: float(np.interp(u, [0.0, 0.5, 0.8, 1.0], [0.16, 0.17, 0.22, 0.09]))
    depth = lambda u: float(np.interp(u, [0.0, 0.5, 0.8, 1.0], [0.10, 0.11, 0.11, 0.10]))
    _tube(m, pts, width, depth, 2, 4, [J("hips"), J("chest"), J("head")], [0.0, 0.5, 0.85, 1.0], [0.0, 0.08, 0.05], _colors(palette)[0], jc,
          cap_start=False, cap_end=False)
    return m.build("zombie_body", "body", 0, (1.0, 1.0, 1.0, 1.0))


def _merged(parts: list[SkinnedMesh], like: SkinnedMesh) -> SkinnedMesh:
    """`parts` as one mesh that stands in for the piece `like` (its name, piece and group)."""
    starts = np.cumsum([0] + [len(p.positions) for p in parts])
    return dataclasses.replace(
        like, positions=np.concatenate([p.positions for p in parts]), normals=np.concatenate([p.normals for p in parts]),
        joints=np.concatenate([p.joints for p in parts]), weights=np.concatenate([p.weights for p in parts]),
        colors=np.concatenate([p.colors for p in parts]), indices=np.concatenate([p.indices + k for p, k in zip(parts, starts)]).astype(np.uint32))


# ------------------------------------------------------------------------------------------------
# Morph targets (issue 23): each a displacement field in bind space, applied to every piece and LOD
# alike (the shadow proxy too), so a piece's LODs share its shapes by construction. The clips key
# "snarl" (below); the others are a body variation a scene gives each zombie (crowd.anim.morph).

MORPH_TARGETS = ("snarl", "belly_swell", "chest_sunken", "gaunt")


def _morph_displacements(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(T, V, 3) displacements of bind positions `p` with normals `n` at weight 1."""
    out = np.zeros((len(MORPH_TARGETS), len(p), 3))
    x, y, z = p[:, 0], p[:, 1], p[:, 2]

    def blob(centre, radii):
        d = (p - np.asarray(centre)) / np.asarray(radii)
        return _smoothstep(1.0 - np.sqrt(np.sum(d * d, axis=1)))

    # Snarl: the upper lip and nose pulled up and back, the lower lip down, the cheeks up.
    upper = blob((0.0, 1.68, 0.10), (0.055, 0.03, 0.06))
    lower = blob((0.0, 1.645, 0.10), (0.045, 0.02, 0.06))
    cheeks = blob((0.045, 1.675, 0.085), (0.03, 0.03, 0.05)) + blob((-0.045, 1.675, 0.085), (0.03, 0.03, 0.05))
    out[0] = upper[:, None] * [0.0, 0.012, -0.006] + lower[:, None] * [0.0, -0.010, 0.002] + cheeks[:, None] * [0.0, 0.008, -0.004]
    # The torso's own region: the arms (out past the shoulders in the T-pose) and the legs below the hips stay.
    torso = _smoothstep((0.24 - np.abs(x)) / 0.06) * _smoothstep((y - 0.80) / 0.1)
    radial = np.stack([x, np.zeros_like(x), z + 0.01], axis=1)
    radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9)
    front = np.maximum(radial[:, 2], 0.0)
    # Swollen belly: out around the navel, most to the front.
    out[1] = radial * (0.07 * np.exp(-(((y - 1.05) / 0.1) ** 2)) * (0.3 + 0.7 * front) * torso)[:, None]
    # Sunken chest: the breastbone in.
    out[2] = -radial * (0.035 * np.exp(-(((y - 1.33) / 0.07) ** 2)) * front ** 2 * torso)[:, None]
    # Gaunt: the torso, neck and face 1.2 cm in along their normals (the limbs are thin already).
    out[3] = -n * (0.012 * _smoothstep((0.26 - np.abs(x)) / 0.05) * _smoothstep((y - 0.85) / 0.1))[:, None]
    return out


def with_targets(mesh: SkinnedMesh, displacements: np.ndarray | None = None) -> SkinnedMesh:
    """`mesh` with the zombie's morph targets: position deltas as given (default its own bind
    displacements), normal deltas the change of its smooth normals; quantised as positions are."""
    p = np.asarray(mesh.positions, np.float64)
    idx = mesh.indices.astype(np.int64)
    d = _morph_displacements(p, np.asarray(mesh.normals, np.float64)) if displacements is None else displacements
    d = _quantise(d, 1e-6)
    base = vertex_normals(p, idx)
    normals = np.stack([_quantise(vertex_normals(p + dk, idx) - base, 1e-6) for dk in d])
    return dataclasses.replace(mesh, morph_targets=np.arange(len(MORPH_TARGETS)), morph_positions=d.astype(np.float32),
                               morph_normals=normals.astype(np.float32))


# Each clip's snarl, by phase: slack while wandering, bared while chasing, widest at an attack's strike.
# The AI cross-fades the clips (crowd.sim.ai), and their snarls with them: that is how it sets the face.
SNARL = {
    "idle": lambda p: 0.1 + 0.05 * np.sin(TAU * p),
    "shamble": lambda p: 0.2 + 0.05 * np.sin(2 * TAU * p),
    "run": lambda p: 0.85 + 0.15 * np.sin(2 * TAU * p),
    "attack": lambda p: np.interp(p, [0.0, 0.3, 0.48, 0.8, 1.0], [0.4, 0.9, 1.0, 0.6, 0.4]),
    "hit": lambda p: np.interp(p, [0.0, 0.2, 1.0], [0.3, 0.8, 0.4]),
    "death": lambda p: np.interp(p, [0.0, 0.3, 1.0], [0.6, 0.8, 0.0]),
    "crawl": lambda p: 0.5 + 0.1 * np.sin(TAU * p),
}


def build_meshes(palette: Palette = ZOMBIE_PALETTE) -> list[SkinnedMesh]:
    meshes = []
    for lod, div in enumerate(LOD_DIVISORS):
        built = [build(div) for build in (lambda d: _build_body(d, palette), lambda d: _build_head(d, "head_a", palette),
                                          lambda d: _build_head(d, "head_b", palette), lambda d: _build_shirt(d, palette))]
        if div == LOD_DIVISORS[-1]:
            # LOD3 (the far crowd): each head choice's whole figure as one mesh under the head's piece
            # name, so a far agent is one instance of one draw, not three. The H200 draws many small
            # instances below its triangle rate (docs/BENCHMARKS.md, "The coarse LOD").
            body, head_a, head_b, shirt = built
            built = [_merged([body, head, shirt], head) for head in (head_a, head_b)]
        for mesh in built:
            mesh.lod = lod
            mesh.name = f"{mesh.name}_lod{lod}"
            meshes.append(with_targets(mesh))
    proxy = _build_shadow_proxy(palette)
    proxy.lod = len(LOD_DIVISORS)
    proxy.name = f"{proxy.name}_lod{proxy.lod}"
    return meshes + [with_targets(proxy)]  # (its shadow swells with the belly too)


# ------------------------------------------------------------------------------------------------
# Other builds of the rig (crowd.asset.brute, crowd.asset.survivor): the same joints at other rest
# positions, and the zombie's meshes moved onto them.

# The bone each joint's vertices scale about: its own (to the child named here), else (a leaf: the
# head, the jaw, the left hand, the socket, the toes) its parent's.
_CHILD = {"hips": "spine", "spine": "chest", "chest": "neck", "neck": "head", "hand_r": "hand_r_socket",
          **{f"{a}_{s}": f"{b}_{s}" for s in "lr" for a, b in (("shoulder", "upper_arm"), ("upper_arm", "forearm"), ("forearm", "hand"),
                                                              ("thigh", "shin"), ("shin", "foot"), ("foot", "toe"))}}


def _scale_about_bones(body: Body, girth: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per joint: the zombie's rest position, `body`'s, and the 3x3 scale about the joint's bone: along
    the bone by its change in length, across it by the joint's `girth` (x, y, z: the components across
    the bone, in model axes at rest; by joint name, or its name without the side)."""
    names = JOINT_NAMES
    before, after = ZOMBIE_BODY.positions(), body.positions()
    parents = [names.index(p) if p else -1 for _, p, _ in ZOMBIE_BODY.joints]
    scales = np.zeros((len(names), 3, 3))
    for j, name in enumerate(names):
        base = name[:-2] if name.endswith(("_l", "_r")) else name
        if name in _CHILD:
            c = names.index(_CHILD[name])
            bone_before, bone_after = before[c] - before[j], after[c] - after[j]
        else:  # a leaf: its parent's bone
            p = parents[j]
            bone_before, bone_after = before[j] - before[p], after[j] - after[p]
        d = bone_before / np.linalg.norm(bone_before)
        along = np.linalg.norm(bone_after) / np.linalg.norm(bone_before)
        across = np.eye(3) - np.outer(d, d)
        scales[j] = along * np.outer(d, d) + across @ np.diag(girth.get(name, girth[base])) @ across
    return before, after, scales


def remodel(mesh: SkinnedMesh, body: Body, girth: dict, name: str, targets: bool = True) -> SkinnedMesh:
    """A zombie mesh on `body`'s skeleton: each vertex moved by its joints' moves (position, and scale
    about the bone), blended by its own skin weights, as skinning blends; normals made anew; quantised
    as the zombie's are; its morph targets carried over (or left out: `targets` False). Named after
    `name` instead of the zombie."""
    before, after, scales = _scale_about_bones(body, girth)
    p = np.asarray(mesh.positions, np.float64)
    moved = np.zeros_like(p)
    for k in range(mesh.joints.shape[1]):
        j = mesh.joints[:, k].astype(np.int64)
        w = mesh.weights[:, k].astype(np.float64)[:, None]
        moved += w * (after[j] + np.einsum("vij,vj->vi", scales[j], p - before[j]))
    total = np.sum(mesh.weights, axis=1, dtype=np.float64)[:, None]
    moved = _quantise(moved / total, 1e-6)
    normals = _quantise(vertex_normals(moved, mesh.indices.astype(np.int64)), 1e-6)
    out = SkinnedMesh(name=mesh.name.replace("zombie_", f"{name}_"), piece=mesh.piece, lod=mesh.lod, positions=moved.astype(np.float32),
                      normals=normals.astype(np.float32), joints=mesh.joints, weights=mesh.weights, indices=mesh.indices, colors=mesh.colors,
                      base_color=mesh.base_color, group=mesh.group)
    if not targets or not mesh.morph_count:
        return out
    # A target's deltas move as its vertex's neighbourhood does: by the linear part of the same blend.
    deltas = np.zeros(mesh.morph_positions.shape)
    for k in range(mesh.joints.shape[1]):
        j = mesh.joints[:, k].astype(np.int64)
        w = mesh.weights[:, k].astype(np.float64)[:, None]
        deltas += w * np.einsum("vij,tvj->tvi", scales[j], np.asarray(mesh.morph_positions, np.float64))
    return with_targets(out, deltas / total)


# ------------------------------------------------------------------------------------------------
# Weapons: handle along +Y, grip at the origin.


def _rigid_from_builder(m: _MeshBuilder, name: str, color) -> RigidMesh:
    sk = m.build(name, name, 0, color)
    return RigidMesh(name, sk.positions, sk.normals, sk.indices, sk.colors, color)


def _build_weapons(div: int) -> tuple[RigidMesh, RigidMesh]:
    """The pipe and the axe, with rings and sides divided by `div` (the agent's LOD divisor)."""
    jc = 1
    one = lambda pos, u: np.concatenate([np.repeat(np.array([[0.35, 0.22, 0.15]]), pos.shape[0], 0), np.ones((pos.shape[0], 1))], 1)
    suffix = f"_lod{LOD_DIVISORS.index(div)}" if div > 1 else ""
    caps = {} if div <= 4 else {"cap_start": False, "cap_end": False}  # LOD3's ends are under a pixel: half its triangles
    m = _MeshBuilder()
    pipe = np.array([[0.0, -0.10, 0.0], [0.0, 0.80, 0.0]])
    rust = lambda pos, u: np.concatenate([(np.array([0.42, 0.25, 0.16]) * (0.75 + 0.25 * _noise(9, pos[:, 1] * 40.0))[:, None]), np.ones((pos.shape[0], 1))], 1)
    _tube(m, pipe, lambda u: 0.017, lambda u: 0.017, 8 // div, 12 // div, [0], [0.0, 1.0], [0.0], rust, jc, **caps)
    elbow = np.array([[0.0, 0.78, 0.0], [0.0, 0.80, 0.02], [0.0, 0.80, 0.10]])
    _tube(m, elbow, lambda u: 0.02, lambda u: 0.02, 4 // div, 12 // div, [0], [0.0, 1.0], [0.0], rust, jc, **caps)
    pipe_mesh = _rigid_from_builder(m, "weapon_pipe" + suffix, (1.0, 1.0, 1.0, 1.0))

    m = _MeshBuilder()
    handle = np.array([[0.0, -0.12, 0.0], [0.0, 0.62, 0.0]])
    _tube(m, handle, lambda u: 0.018 + 0.004 * u, lambda u: 0.015 + 0.003 * u, 8 // div, 10 // div, [0], [0.0, 1.0], [0.0], one, jc, **caps)
    # The head: a wedge blade pointing +Z (the blade faces where the palm's thumb side points).
    steel = lambda pos, u: np.concatenate([np.repeat(np.array([[0.55, 0.57, 0.6]]), pos.shape[0], 0), np.ones((pos.shape[0], 1))], 1)
    blade = np.array([[0.0, 0.56, -0.04], [0.0, 0.58, 0.06], [0.0, 0.56, 0.16]])
    _tube(m, blade, lambda u: 0.012 - 0.009 * u, lambda u: 0.06 + 0.06 * u, 6 // div, 8 // div, [0], [0.0, 1.0], [0.0], steel, jc, **caps)
    return pipe_mesh, _rigid_from_builder(m, "weapon_axe" + suffix, (1.0, 1.0, 1.0, 1.0))


def build_props() -> dict[str, Prop]:
    """The weapons at every LOD divisor: a far agent's weapon has as few triangles as its hand."""
    (pipe_mesh, axe_mesh), *coarser = [_build_weapons(div) for div in LOD_DIVISORS]
    # Grip frames: where the fist closes on the handle, in the prop's own space.
    pipe_grip = np.eye(4)
    pipe_grip[1, 3] = 0.02
    axe_grip = np.eye(4)
    axe_grip[1, 3] = 0.0
    return {"pipe": Prop(pipe_mesh, pipe_grip, tuple(c[0] for c in coarser)), "axe": Prop(axe_mesh, axe_grip, tuple(c[1] for c in coarser))}


# ------------------------------------------------------------------------------------------------
# Clips. A pose is a handful of named angles (radians) and a hips offset (metres); clips are functions
# of phase p in [0, 1) that return those parameters, turned into joint rotations by _pose_to_joints.
# Conventions at rest (world-aligned joint axes): a positive *_pitch leans forward, thigh_flex swings
# the leg forward, knee bends the shin back, ankle points the toes down, arm_down lowers the arm from
# the T-pose, arm_fwd swings it forward, elbow bends the forearm, wrist droops the hand.

_PARAMS = (
    "hips_x hips_y hips_z hips_pitch hips_yaw hips_roll spine_pitch spine_yaw chest_pitch chest_yaw chest_roll "
    "neck_pitch head_pitch head_roll head_yaw jaw"
).split()
_SIDE_PARAMS = "shrug arm_down arm_fwd arm_twist elbow wrist thigh_flex thigh_twist thigh_abd knee ankle toe".split()
TAU = 2.0 * math.pi


def _neutral(n: int) -> dict[str, np.ndarray]:
    p = {k: np.zeros(n) for k in _PARAMS}
    for s in "lr":
        for k in _SIDE_PARAMS:
            p[f"{k}_{s}"] = np.zeros(n)
        p[f"arm_down_{s}"] = np.full(n, 1.3)  # arms hang by default
        p[f"elbow_{s}"] = np.full(n, 0.25)
    return p


def _q(x=0.0, y=0.0, z=0.0, order="xyz") -> np.ndarray:
    qx = tf.quat_from_axis_angle([1.0, 0.0, 0.0], np.asarray(x, dtype=np.float64))
    qy = tf.quat_from_axis_angle([0.0, 1.0, 0.0], np.asarray(y, dtype=np.float64))
    qz = tf.quat_from_axis_angle([0.0, 0.0, 1.0], np.asarray(z, dtype=np.float64))
    if order == "xyz":  # apply x, then y, then z
        return tf.quat_mul(qz, tf.quat_mul(qy, qx))
    if order == "xzy":  # apply x, then z, then y
        return tf.quat_mul(qy, tf.quat_mul(qz, qx))
    raise ValueError(order)


def _mirror(q: np.ndarray) -> np.ndarray:
    """Mirror a left-side rotation to the right side (reflection through the YZ plane)."""
    q = q.copy()
    q[..., 1] *= -1.0
    q[..., 2] *= -1.0
    return q


def _pose_to_joints(p: dict[str, np.ndarray], n: int, body: Body = ZOMBIE_BODY) -> tuple[dict[str, np.ndarray], np.ndarray]:
    p = {k: np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)).copy() for k, v in p.items()}
    out = {
        "hips": _q(p["hips_pitch"], p["hips_yaw"], p["hips_roll"], "xzy"),
        "spine": _q(p["spine_pitch"], p["spine_yaw"], 0.0),
        "chest": _q(p["chest_pitch"], p["chest_yaw"], p["chest_roll"]),
        "neck": _q(p["neck_pitch"], 0.5 * p["head_yaw"], 0.0),
        "head": _q(p["head_pitch"], 0.5 * p["head_yaw"], p["head_roll"]),
        "jaw": _q(p["jaw"], 0.0, 0.0),
    }
    for s in "lr":
        g = lambda k: p[f"{k}_{s}"]
        shoulder = _q(0.0, -0.3 * g("arm_fwd") * 0.3, 0.4 * g("shrug"))
        # Twist about the bone, then lower, then swing forward (in the shoulder's frame).
        arm = _q(g("arm_twist"), -g("arm_fwd"), -g("arm_down"), "xzy")
        forearm = _q(0.0, -g("elbow"), 0.0)
        hand = _q(0.0, 0.0, -g("wrist"))
        thigh = _q(-g("thigh_flex"), g("thigh_twist"), g("thigh_abd"))
        shin = _q(g("knee"), 0.0, 0.0)
        foot = _q(g("ankle"), 0.0, 0.0)
        toe = _q(g("toe"), 0.0, 0.0)
        for name, q in (("shoulder", shoulder), ("upper_arm", arm), ("forearm", forearm), ("hand", hand),
                        ("thigh", thigh), ("shin", shin), ("foot", foot), ("toe", toe)):
            out[f"{name}_{s}"] = q if s == "l" else _mirror(q)
    hips_t = np.stack([p["hips_x"], p["hips_y"], p["hips_z"]], axis=1) + _joint_positions(body)[0]
    return out, hips_t


def _bump(p, centre, width):
    """A smooth periodic bump in phase, peaking at `centre`."""
    d = np.mod(p - centre + 0.5, 1.0) - 0.5
    return np.exp(-((d / width) ** 2))


def _ease_keys(p, times, values):
    """Piecewise ease-in-out between key poses (times in [0, 1], values per key)."""
    p = np.asarray(p, dtype=np.float64)
    out = np.empty_like(p)
    for i, x in enumerate(p):
        k = int(np.clip(np.searchsorted(times, x, side="right") - 1, 0, len(times) - 2))
        u = (x - times[k]) / (times[k + 1] - times[k])
        u = float(np.clip(u, 0.0, 1.0))
        u = u * u * (3 - 2 * u)
        out[i] = values[k] + (values[k + 1] - values[k]) * u
    return out


def _keyed(p, keys: list[tuple[float, dict[str, float]]], base: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Override parameters with eased key poses; a key lists only the parameters it changes."""
    names = set().union(*(k[1].keys() for k in keys))
    for name in names:
        times, vals, last = [], [], None
        for t, pose in keys:
            last = pose.get(name, last if last is not None else float(np.ravel(base[name])[0]))
            times.append(t)
            vals.append(last)
        base[name] = _ease_keys(p, np.array(times), np.array(vals))
    return base


# ------------------------------------------------------------------------------------------------
# Planted feet (issue 21, point 2). The legs of the locomotion clips and of idle are not keyed by angle:
# each foot follows a path in model space that keeps it still in world space while it carries weight,
# and the leg's angles are solved for it by inverse kinematics. Keyed angles had let feet slide 33 cm
# for every metre walked (docs/ACCURACY.md, "Foot skate").
#
# The path of one foot over a cycle, for a body moving forward at `stride` metres a cycle:
# - stance, for `duty` of the cycle around its mid-stance phase: flat on the ground, still in world
#   space, so in model space it moves backward at exactly the body's speed;
# - swing: for the first and last `lift` share of the swing it rises (or comes down) straight up in
#   world space, still over the same spot; in between it travels forward one stride, toes pitched down.
# A foot below the contact height (3 cm above its lowest) therefore never moves horizontally in world
# space, which is what crowd-bench skate measures (the 30 fps keys' interpolation leaves 0.4 to 0.6
# cm/m). Both clips keep their mid-stances at the same phases, so that in a walk-run blend (one phase
# for both) their stance feet move together.


@dataclasses.dataclass(frozen=True)
class _Gait:
    stride: float  # metres the body covers a cycle (the clip's stride)
    duty: float  # share of the cycle a foot carries weight
    lift: float  # share of the swing, at each end, in which the foot moves only up or down
    mid_stance: float  # phase of the left foot's mid-stance; the right one's is half a cycle later
    height: tuple[float, float]  # swing height of the ankle (left, right), metres
    toe_down: tuple[float, float]  # toes-down pitch at mid-swing (left, right), radians
    toe_out: tuple[float, float]  # yaw of each foot, toes outward, radians
    width: float = 0.10  # the feet's distance from the midline
    reach: float = 0.0  # model-space z of the ankle at mid-stance
    direction: float = 0.0  # radians from +Z (forward) toward +X (the left) that the body travels: pi / 2 steps sideways to the left




def _smootherstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _foot_path(g: _Gait, side: int, p: np.ndarray, body: Body = ZOMBIE_BODY) -> tuple[np.ndarray, np.ndarray]:
    """Model-space targets (n, 3) of one foot's ankle and toe joints at phases `p` (side 0 left, 1 right)."""
    mid = g.mid_stance + 0.5 * side
    delta = np.mod(p - mid + 0.5, 1.0) - 0.5  # phase since mid-stance, in [-0.5, 0.5)
    stance = np.abs(delta) <= 0.5 * g.duty
    u = np.where(stance, 0.0, np.mod(delta - 0.5 * g.duty, 1.0) / (1.0 - g.duty))  # share of the swing done
    travel = _smootherstep((u - g.lift) / (1.0 - 2.0 * g.lift))  # share of the stride travelled in world space
    since_mid = np.where(stance, delta, 0.5 * g.duty + u * (1.0 - g.duty))  # body travel since mid-stance, cycles
    d = g.stride * (travel - since_mid)  # the foot's travel from its mid-stance place, along the body's direction
    z = g.reach + math.cos(g.direction) * d
    # Straight up (or down) to the swing's height, which clears the contact height at once even in a
    # blend that gives this clip a small weight, then forward in a low arc.
    rise = np.minimum(_smootherstep(u / g.lift), _smootherstep((1.0 - u) / g.lift))
    rise = np.where(stance, 0.0, rise)
    y = body.stance_ankle_y + g.height[side] * rise * (1.0 + 0.25 * np.sin(math.pi * travel))
    sign = 1.0 if side == 0 else -1.0
    ankle = np.stack([sign * g.width + math.sin(g.direction) * d, y, z], axis=1)
    pitch = np.where(stance, 0.0, g.toe_down[side] * np.sin(math.pi * travel) ** 2)
    return ankle, _toe_of(ankle, pitch, np.full_like(p, sign * g.toe_out[side]), body)


def _toe_of(ankle: np.ndarray, pitch, yaw, body: Body = ZOMBIE_BODY) -> np.ndarray:
    """Where the toe joint is for a foot at `ankle` (n, 3), pitched toes down by `pitch` and turned by `yaw`."""
    return ankle + tf.quat_rotate(_q(pitch, yaw, 0.0), np.array(body.toe_from_ankle))


def _leg(skeleton: Skeleton, s: str) -> tuple[int, float, float]:
    """A leg's thigh joint and its upper and lower bone lengths (side "l" or "r")."""
    length = lambda name: float(np.linalg.norm(skeleton.rest_translation[skeleton.index(f"{name}_{s}")]))
    return skeleton.index(f"thigh_{s}"), length("shin"), length("foot")


def _hip_joints(skeleton: Skeleton, a: dict[str, np.ndarray], n: int, body: Body = ZOMBIE_BODY) -> list[np.ndarray]:
    """Model-space positions (n, 3) of the left and right thigh joints under the pose `a`."""
    rot, hips_t = _pose_to_joints(a, n, body)
    g = _globals(skeleton, rot, hips_t)
    return [g[:, _leg(skeleton, s)[0], :3, 3] for s in "lr"]


_LEG_PARAMS = ("thigh_flex", "thigh_twist", "thigh_abd", "knee", "ankle")


def _guess_legs(skeleton: Skeleton, a: dict[str, np.ndarray], targets, n: int, body: Body = ZOMBIE_BODY) -> None:
    """A starting point for _plant, in place: each leg bent in its own plane, knee forward, as the law
    of cosines gives it for the hip-to-ankle distance (hips rotation ignored; the solver corrects it)."""
    hips = _hip_joints(skeleton, a, n, body)  # the leg's own angles do not move its hip joint
    toe_from_ankle = body.toe_from_ankle
    for side, s in enumerate("lr"):
        _, upper, lower = _leg(skeleton, s)
        d = targets[side][0] - hips[side]
        dist = np.clip(np.linalg.norm(d, axis=1), abs(upper - lower) + 1e-3, upper + lower - 1e-4)
        bend = math.pi - np.arccos((upper * upper + lower * lower - dist * dist) / (2 * upper * lower))
        lean = np.arcsin(np.clip(lower * np.sin(bend) / dist, -1.0, 1.0))  # thigh ahead of the hip-ankle line
        a[f"thigh_flex_{s}"] = np.arctan2(d[:, 2], -d[:, 1]) + lean
        a[f"knee_{s}"] = bend
        a[f"thigh_abd_{s}"] = np.zeros(n)
        a[f"thigh_twist_{s}"] = np.zeros(n)
        toe = targets[side][1] - targets[side][0]
        pitch = np.arctan2(-toe[:, 1], toe[:, 2]) - math.atan2(-toe_from_ankle[1], toe_from_ankle[2])
        a[f"ankle_{s}"] = pitch - (a["hips_pitch"] - a[f"thigh_flex_{s}"] + bend)


def _plant(p: np.ndarray, a: dict[str, np.ndarray], targets, iterations: int = 200, body: Body = ZOMBIE_BODY) -> dict[str, np.ndarray]:
    """Solve both legs' angles (`_LEG_PARAMS`) so that the ankle and toe joints reach `targets`
    ((ankle, toe) per side, each (n, 3)), with the rest of the pose `a` as it is, starting from
    _guess_legs (which picks the knee-forward solution). Damped Gauss-Newton on a numerical Jacobian:
    the generator runs once, and the two legs are independent, so one pose evaluation perturbs the same
    angle of both."""
    skeleton = _skeleton(body)
    n = p.shape[0]
    joints = [[skeleton.index(f"foot_{s}"), skeleton.index(f"toe_{s}")] for s in "lr"]
    goal = np.stack([np.concatenate(t, axis=1) for t in targets])  # (2, n, 6)

    def residual(params):
        rot, hips_t = _pose_to_joints(params, n, body)
        g = _globals(skeleton, rot, hips_t)
        return np.stack([np.concatenate([g[:, j, :3, 3] for j in js], axis=1) for js in joints]) - goal

    a = {k: np.array(v, dtype=np.float64, copy=True) for k, v in a.items()}
    _guess_legs(skeleton, a, targets, n, body)
    eps, eye = 1e-6, np.eye(len(_LEG_PARAMS))
    damping = np.full((2, n), 1e-3)  # Levenberg-Marquardt: per side and key, lowered on success
    r = residual(a)
    cost = np.sum(r * r, axis=-1)
    for _ in range(iterations):
        if np.max(np.abs(r)) < 1e-9:
            break
        jac = np.empty((2, n, 6, len(_LEG_PARAMS)))
        for k, name in enumerate(_LEG_PARAMS):
            moved = dict(a)
            for s in "lr":
                moved[f"{name}_{s}"] = a[f"{name}_{s}"] + eps
            jac[..., k] = (residual(moved) - r) / eps
        jt = np.swapaxes(jac, -1, -2)
        jtj = jt @ jac
        step = np.linalg.solve(jtj + damping[..., None, None] * eye, -(jt @ r[..., None]))[..., 0]
        trial = dict(a)
        for i, s in enumerate("lr"):
            for k, name in enumerate(_LEG_PARAMS):
                trial[f"{name}_{s}"] = a[f"{name}_{s}"] + step[i, :, k]
        r_trial = residual(trial)
        cost_trial = np.sum(r_trial * r_trial, axis=-1)
        better = cost_trial < cost
        for i, s in enumerate("lr"):
            for name in _LEG_PARAMS:
                key = f"{name}_{s}"
                a[key] = np.where(better[i], trial[key], a[key])
        r = np.where(better[..., None], r_trial, r)
        cost = np.where(better, cost_trial, cost)
        damping = np.where(better, damping / 3.0, damping * 4.0)
    worst = float(np.max(np.abs(residual(a))))
    if worst > 1e-6:  # a foot out of the leg's reach: the gait's hips are too high for its stride
        raise AssertionError(f"the legs do not reach their feet: {worst * 1000:.3f} mm off")
    return a


def _planted(p: np.ndarray, a: dict[str, np.ndarray], gait: _Gait, body: Body = ZOMBIE_BODY) -> dict[str, np.ndarray]:
    targets = [_foot_path(gait, side, p, body) for side in (0, 1)]
    a = dict(a)
    a["hips_y"] = np.asarray(a["hips_y"], np.float64) - _reach_drop(a, targets, p.shape[0], body=body)
    return _plant(p, a, targets, body=body)


def _reach_drop(a: dict[str, np.ndarray], targets, n: int, slack: float = 0.985, body: Body = ZOMBIE_BODY) -> np.ndarray:
    """How far to lower the hips at each key of a loop so that both ankles are within `slack` of the
    leg's full length (a straight knee is a singular, snapping pose): the largest need nearby, smoothed,
    so the hips do not jerk."""
    skeleton = _skeleton(body)
    hips = _hip_joints(skeleton, a, n, body)
    need = np.zeros(n)
    for side, s in enumerate("lr"):
        _, upper, lower = _leg(skeleton, s)
        leg = slack * (upper + lower)
        d = targets[side][0] - hips[side]
        flat = np.minimum(d[:, 0] ** 2 + d[:, 2] ** 2, leg * leg)
        need = np.maximum(need, np.maximum(0.0, -d[:, 1] - np.sqrt(leg * leg - flat)))
    widened = np.max([np.roll(need, k) for k in range(-3, 4)], axis=0)
    return np.mean([np.roll(widened, k) for k in range(-2, 3)], axis=0)


SHAMBLE_GAIT = _Gait(stride=0.9, duty=0.6, lift=0.2, mid_stance=0.3, height=(0.09, 0.07), toe_down=(0.25, 0.2),
                     toe_out=(0.1, 0.25))
RUN_GAIT = _Gait(stride=2.3, duty=0.3, lift=0.08, mid_stance=0.3, height=(0.22, 0.22), toe_down=(0.5, 0.5),
                 toe_out=(0.08, 0.08))


def _standing(p: np.ndarray, a: dict[str, np.ndarray], toe_out=(0.12, 0.2), reach=(0.02, -0.03), body: Body = ZOMBIE_BODY) -> dict[str, np.ndarray]:
    """Both feet flat and still where they stand (idle sways its hips over them)."""
    targets = []
    for side in (0, 1):
        sign = 1.0 if side == 0 else -1.0
        ankle = np.tile([sign * body.stance_width, body.stance_ankle_y, reach[side]], (p.shape[0], 1))
        targets.append((ankle, _toe_of(ankle, 0.0, np.full(p.shape, sign * toe_out[side]), body)))
    return _plant(p, a, targets, body=body)


def _shamble(p):
    a = _neutral(p.shape[0])
    c, s = np.cos(TAU * p), np.sin(TAU * p)
    a["hips_x"] = 0.035 * s
    a["hips_pitch"] = 0.12 + 0.02 * np.cos(2 * TAU * p)
    a["hips_yaw"] = 0.14 * c
    a["hips_roll"] = -0.07 * s
    a["spine_pitch"] = 0.12
    a["chest_pitch"] = 0.22 + 0.03 * np.cos(2 * TAU * p)
    a["chest_yaw"] = -0.12 * c
    a["chest_roll"] = 0.08 + 0.04 * s  # lopsided
    a["neck_pitch"] = -0.25
    a["head_pitch"] = -0.05 + 0.06 * np.cos(2 * TAU * p + 0.6)
    a["head_roll"] = 0.3 + 0.05 * s
    a["jaw"] = 0.18 + 0.08 * np.sin(2 * TAU * p)
    # The left arm reaches forward, the right one hangs and swings: zombies are not symmetric.
    a["arm_down_l"] = -0.35 + 0.06 * np.sin(2 * TAU * p)  # raised against the forward lean: level and reaching
    a["arm_fwd_l"] = 1.3 + 0.05 * c
    a["arm_twist_l"] = -0.6
    a["elbow_l"] = 0.2 + 0.05 * s
    a["wrist_l"] = 0.5
    a["arm_down_r"] = 0.35 + 0.1 * c
    a["arm_fwd_r"] = 1.0 - 0.2 * c
    a["arm_twist_r"] = -0.4
    a["elbow_r"] = 0.4 + 0.1 * s
    a["wrist_r"] = 0.35
    # The legs are solved for SHAMBLE_GAIT's foot paths: the left one steps high, the right one limps,
    # low and toes down. The hips sit low enough for the legs to reach the ends of the stride.
    a["hips_y"] = -0.08 + 0.03 * np.cos(2 * TAU * (p - SHAMBLE_GAIT.mid_stance))  # highest over a planted foot
    return _planted(p, a, SHAMBLE_GAIT)


def _run(p):
    a = _neutral(p.shape[0])
    p_strike = p - RUN_GAIT.mid_stance + 0.5 * RUN_GAIT.duty  # phase since the left heel strike
    c, s = np.cos(TAU * p_strike), np.sin(TAU * p_strike)
    a["hips_x"] = 0.025 * s
    a["hips_pitch"] = 0.25
    a["hips_yaw"] = 0.2 * c
    a["spine_pitch"] = 0.15
    a["chest_pitch"] = 0.35
    a["chest_yaw"] = -0.25 * c
    a["neck_pitch"] = -0.45
    a["head_pitch"] = -0.1 + 0.08 * np.cos(2 * TAU * p)
    a["head_roll"] = 0.15 * s
    a["jaw"] = 0.45
    # Arms flail forward, clawing.
    a["arm_down_l"] = 0.55 - 0.35 * c
    a["arm_fwd_l"] = 1.0 - 0.5 * c
    a["elbow_l"] = 0.9 + 0.4 * c
    a["wrist_l"] = 0.4
    a["arm_down_r"] = 0.55 + 0.35 * c
    a["arm_fwd_r"] = 1.0 + 0.5 * c
    a["elbow_r"] = 0.9 - 0.4 * c
    a["wrist_r"] = 0.4
    a["hips_y"] = -0.15 + 0.03 * np.cos(2 * TAU * (p - RUN_GAIT.mid_stance))  # _planted lowers it where the stride needs
    return _planted(p, a, RUN_GAIT)


def _idle(p):
    a = _neutral(p.shape[0])
    s = np.sin(TAU * p)
    a["hips_x"] = 0.02 * s
    a["hips_roll"] = -0.04 * s
    a["spine_pitch"] = 0.1
    a["chest_pitch"] = 0.18 + 0.03 * np.sin(2 * TAU * p)  # laboured breathing
    a["chest_roll"] = 0.06
    a["neck_pitch"] = -0.05
    a["head_pitch"] = 0.25 + 0.1 * np.sin(TAU * p + 1.0)
    a["head_roll"] = 0.35 + 0.15 * s
    a["head_yaw"] = 0.15 * np.sin(TAU * p + 0.5)
    a["jaw"] = 0.25 + 0.15 * np.sin(3 * TAU * p)
    for side, ph in (("l", 0.0), ("r", 0.9)):
        a[f"arm_down_{side}"] = 1.3 + 0.05 * np.sin(TAU * p + ph)
        a[f"arm_fwd_{side}"] = 0.25 + 0.08 * np.sin(TAU * p + ph)
        a[f"elbow_{side}"] = 0.3 + 0.05 * np.sin(TAU * p + ph + 0.5)
        a[f"wrist_{side}"] = 0.3
    a["hips_y"] = -0.03  # knees a little bent over the planted feet
    return _standing(p, a)


def _attack(p):
    """Overhead swing with the right (weapon) hand: wind up, strike down, recover."""
    a = _idle(np.zeros_like(p))
    keys = [
        (0.0, {}),
        (0.3, dict(arm_down_r=-1.4, arm_fwd_r=0.7, arm_twist_r=-0.6, elbow_r=1.1, wrist_r=-0.3, chest_yaw=0.45, chest_pitch=-0.05,
                   spine_yaw=0.2, head_pitch=0.0, jaw=0.6, thigh_flex_r=-0.15, knee_r=0.3, thigh_flex_l=0.25)),
        (0.48, dict(arm_down_r=0.9, arm_fwd_r=1.5, arm_twist_r=0.2, elbow_r=0.15, wrist_r=0.3, chest_yaw=-0.5, chest_pitch=0.45,
                    spine_yaw=-0.2, spine_pitch=0.2, head_pitch=0.2, jaw=0.7, arm_down_l=1.0, arm_fwd_l=0.2, thigh_flex_l=0.45, knee_l=0.35,
                    hips_pitch=0.15)),
        (0.62, dict(arm_down_r=1.15, arm_fwd_r=1.0, elbow_r=0.3, chest_yaw=-0.35, chest_pitch=0.38)),
        (1.0, {}),
    ]
    # The last key returns to the idle pose at p = 0 so that cross-fades in and out are clean.
    return _keyed(p, keys, a)


def _hit(p):
    a = _idle(np.zeros_like(p))
    keys = [
        (0.0, {}),
        (0.18, dict(chest_pitch=-0.3, spine_pitch=-0.15, head_pitch=-0.55, head_roll=0.6, hips_z=-0.06, hips_pitch=-0.1, jaw=0.6,
                    arm_down_l=0.4, arm_fwd_l=-0.3, elbow_l=0.6, arm_down_r=0.5, arm_fwd_r=-0.2, elbow_r=0.7, knee_l=0.35, knee_r=0.3,
                    thigh_flex_l=0.25)),
        (0.45, dict(chest_pitch=0.3, head_pitch=0.35, head_roll=0.2, hips_z=-0.04, arm_down_l=1.1, arm_down_r=1.2, elbow_l=0.4)),
        (1.0, {}),
    ]
    return _keyed(p, keys, a)


def _death(p):
    """Knees buckle, the body topples backwards and lies still on its back."""
    a = _idle(np.zeros_like(p))
    keys = [
        (0.0, {}),
        (0.15, dict(chest_pitch=-0.35, head_pitch=-0.6, head_roll=0.5, hips_z=-0.05, jaw=0.8, arm_down_l=0.5, arm_down_r=0.6,
                    arm_fwd_l=-0.2, arm_fwd_r=-0.1, elbow_l=0.8, elbow_r=0.6)),
        (0.35, dict(hips_y=-0.38, hips_pitch=0.15, chest_pitch=0.25, head_pitch=0.5, knee_l=1.9, knee_r=1.7, thigh_flex_l=1.1,
                    thigh_flex_r=1.0, ankle_l=-0.55, ankle_r=-0.5, arm_down_l=1.2, arm_down_r=1.3, arm_fwd_l=0.3, arm_fwd_r=0.2)),
        (0.62, dict(hips_y=-0.84, hips_z=-0.55, hips_pitch=-1.5, chest_pitch=-0.05, spine_pitch=0.0, head_pitch=-0.3, head_roll=0.6,
                    knee_l=0.5, knee_r=0.7, thigh_flex_l=0.4, thigh_flex_r=0.6, ankle_l=0.3, ankle_r=0.4, arm_down_l=0.1,
                    arm_down_r=-0.1, arm_fwd_l=-0.6, arm_fwd_r=-0.5, elbow_l=0.3, elbow_r=0.5, jaw=0.5)),
        (0.72, dict(hips_y=-0.80, head_pitch=-0.2)),
        (0.85, dict(hips_y=-0.85, head_pitch=-0.35, knee_l=0.35, knee_r=0.5, thigh_flex_l=0.3, thigh_flex_r=0.45, ankle_l=0.5,
                    ankle_r=0.6, arm_down_l=0.05, arm_down_r=-0.15, wrist_l=0.0, wrist_r=0.0)),
        (1.0, dict()),
    ]
    return _keyed(p, keys, a)


def _crawl(p):
    """Legs useless, pulling itself along with alternating arms (left hand plants at p = 0)."""
    a = _neutral(p.shape[0])
    c, s = np.cos(TAU * p), np.sin(TAU * p)
    a["hips_y"] = -0.73 + 0.015 * np.cos(2 * TAU * p)
    a["hips_pitch"] = 1.42
    a["hips_roll"] = 0.08 * s
    a["spine_pitch"] = -0.1 - 0.05 * np.cos(2 * TAU * p)
    a["chest_pitch"] = -0.2
    a["chest_roll"] = -0.12 * s
    a["chest_yaw"] = 0.1 * c
    a["neck_pitch"] = -0.5
    a["head_pitch"] = -0.35
    a["head_roll"] = 0.2
    a["jaw"] = 0.4 + 0.2 * np.sin(2 * TAU * p)
    for side, ph in (("l", 0.0), ("r", 0.5)):
        cc = np.cos(TAU * (p - ph))
        reach = 0.5 + 0.5 * cc  # 1 when the hand plants far forward
        a[f"arm_down_{side}"] = 0.6 - 1.9 * reach
        a[f"arm_fwd_{side}"] = 0.9 + 0.2 * np.sin(TAU * (p - ph))
        a[f"elbow_{side}"] = 0.25 + 1.0 * (1.0 - reach)
        a[f"wrist_{side}"] = 0.2
        a[f"thigh_flex_{side}"] = -0.1 + 0.08 * cc
        a[f"thigh_abd_{side}"] = 0.12
        a[f"knee_{side}"] = 0.25 + 0.15 * _bump(p, ph + 0.5, 0.15)
        a[f"ankle_{side}"] = 0.9
    return a



def _foot_markers(g: _Gait) -> dict[str, float]:
    """The phases at which each foot comes down (its heel strike)."""
    return {"left_foot_down": float(np.mod(g.mid_stance - 0.5 * g.duty, 1.0)),
            "right_foot_down": float(np.mod(g.mid_stance + 0.5 - 0.5 * g.duty, 1.0))}


# name, authoring function, duration (s), loop, phase markers, stride (m per cycle), keep feet grounded
CLIP_SPECS = [
    ("idle", _idle, 3.0, True, {}, None, False),
    ("shamble", _shamble, 1.6, True, _foot_markers(SHAMBLE_GAIT), SHAMBLE_GAIT.stride, False),
    ("run", _run, 0.7, True, _foot_markers(RUN_GAIT), RUN_GAIT.stride, False),
    ("attack", _attack, 1.2, False, {"impact": 0.48}, None, True),
    ("hit", _hit, 0.6, False, {}, None, True),
    ("death", _death, 2.2, False, {}, None, False),
    ("crawl", _crawl, 2.4, True, {"left_hand_down": 0.0, "right_hand_down": 0.5}, 0.55, False),
]


def _globals(skeleton: Skeleton, joints: dict[str, np.ndarray], hips_t: np.ndarray) -> np.ndarray:
    """Model-space joint matrices (n, J, 4, 4) of n keys of joint rotations and hips positions."""
    n = hips_t.shape[0]
    rot = np.broadcast_to(skeleton.rest_rotation, (n,) + skeleton.rest_rotation.shape).copy()
    for name, q in joints.items():
        rot[:, skeleton.index(name)] = q
    tr = np.broadcast_to(skeleton.rest_translation, (n,) + skeleton.rest_translation.shape).copy()
    tr[:, 0] = hips_t
    return global_matrices(skeleton, LocalPose(tr, rot, np.ones(tr.shape)))


@functools.cache
def _skeleton(body: Body = ZOMBIE_BODY) -> Skeleton:
    """The skeleton the clips are authored on (read only)."""
    return build_skeleton(body)


def _ground(skeleton: Skeleton, joints: dict[str, np.ndarray], hips_t: np.ndarray, body: Body = ZOMBIE_BODY) -> np.ndarray:
    """Lift or drop the hips so the lowest foot point rests on the ground at every key (no floating, no sinking)."""

    g = _globals(skeleton, joints, hips_t)
    # Sole points under the heel and the toe of each foot, in the foot/toe joints' frames.
    lows = []
    for side in "lr":
        heel = g[:, skeleton.index(f"foot_{side}")] @ np.array([*body.heel, 1.0])
        tip = g[:, skeleton.index(f"toe_{side}")] @ np.array([*body.tip, 1.0])
        lows += [heel[:, 1], tip[:, 1]]
    low = np.min(np.stack(lows), axis=0)
    out = hips_t.copy()
    out[:, 1] -= low
    return out


def build_clips(skeleton: Skeleton, specs=None, body: Body = ZOMBIE_BODY, snarl: bool = True) -> list[Clip]:
    """The clips of `specs` (CLIP_SPECS' shape; default the zombie's) on `skeleton`, built for `body`,
    each keying the snarl target where SNARL names it (`snarl` True)."""
    clips = []
    socket = skeleton.index(SOCKET_JOINT)
    for name, fn, duration, loop, markers, stride, grounded in CLIP_SPECS if specs is None else specs:
        count = int(round(duration * SOURCE_FPS)) + 1
        times = np.arange(count) / SOURCE_FPS
        joints, hips_t = _pose_to_joints(fn(times / duration), count, body)
        if grounded:
            hips_t = _ground(skeleton, joints, hips_t, body)
        if loop:  # close the loop exactly: the last key repeats the first
            hips_t[-1] = hips_t[0]
            for q in joints.values():
                q[-1] = q[0]
        channels = [Channel(0, "translation", "LINEAR", times.copy(), _quantise(hips_t, 1e-6))]
        for jname, q in joints.items():
            j = skeleton.index(jname)
            if j == socket:
                continue
            q = tf.align_quat_track(tf.quat_normalize(q))
            channels.append(Channel(j, "rotation", "LINEAR", times.copy(), _quantise(q, 1e-7)))
        channels.sort(key=lambda c: (c.joint, c.path))
        morph = []
        if snarl and name in SNARL:
            morph = [MorphChannel(np.array([MORPH_TARGETS.index("snarl")]), "LINEAR", times.copy(),
                                  _quantise(SNARL[name](times / duration), 1e-6)[:, None])]
        clips.append(Clip(name, channels, 0.0, float(times[-1]), loop, dict(markers), stride, morph))
    return clips


def build_character() -> Character:
    skeleton = build_skeleton()
    return Character(
        name="zombie",
        skeleton=skeleton,
        meshes=build_meshes(),
        clips=build_clips(skeleton),
        props=build_props(),
        sockets={"weapon_r": skeleton.index(SOCKET_JOINT)},
        morphs=MORPH_TARGETS,
        morph_defaults=np.zeros(len(MORPH_TARGETS)),
    ).validate()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="Generate the built-in zombie and write it as a binary glTF.")
    parser.add_argument("--out", type=Path, default=ASSET_PATH, help=f"output .glb (default {ASSET_PATH})")
    args = parser.parse_args(argv)
    from .gltf_write import write_glb

    character = build_character()
    size = write_glb(character, args.out)
    lod_tris = {}
    for m in character.meshes:
        lod_tris.setdefault(m.lod, {})[m.piece] = m.triangle_count
    print(f"wrote {args.out} ({size} bytes): {character.skeleton.joint_count} joints, "
          f"{len(character.clips)} clips, triangles per LOD {json.dumps(lod_tris)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
