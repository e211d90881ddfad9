"""The zombie's weapons, the pipe and the axe, at every LOD: handle along +Y, grip at the origin."""

from __future__ import annotations

import numpy as np

from .mesh_builder import LOD_DIVISORS, _MeshBuilder, _noise, _rigid_from_builder, _tube
from .model import Prop, RigidMesh


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
