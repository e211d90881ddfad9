"""The zombie's skinned meshes: the body, two heads and the torn shirt at each LOD, the far LOD's merged
figures, and the shadow proxy; every one with the morph targets."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .mesh_builder import LOD_DIVISORS, _MeshBuilder, _noise, _smoothstep, _tube
from .model import SkinnedMesh
from .morph_targets import with_targets
from .palette import ZOMBIE_PALETTE, Palette, _colors
from .rig import JOINT_NAMES


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
