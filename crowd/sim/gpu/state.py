"""The crowd's state as the GPU holds it (shaders/sim/agents.glsl): per agent, one vec4 (or ivec4) per
buffer, float32, positions relative to the crowd's origin; and the per-character table the passes read.
Packs a numpy CrowdAI's arrays into those buffers' bytes and unpacks them again under the numpy AI's
names.

Why relative positions: float32 holds 61 µm at 1,000 m from the origin, where a million agents at the
default 6 m² each reach (a world 2,450 m wide: 1,225 m to an edge, 122 µm); the numpy AI's absolute
float64 positions may be anywhere (an origin 10 km out would leave float32 1 mm)."""

from __future__ import annotations

import numpy as np

from ..config import ACTION_ROLES
from ..motion import FOOT_SAMPLES

NEVER = 1e30  # an action that never ends by time (numpy: inf; a fast-math GPU compiler may not keep inf)
# buffer name -> (binding, the numpy AI's arrays in its four columns, dtype); "_x", "_z": less the origin's x or z.
FIELDS = {
    "motion": (0, ("x_x", "z_z", "vx", "vz"), np.float32),
    "heading": (1, ("hx", "hz", "phase", "scale"), np.float32),
    "timers": (2, ("state_time", "action_time", "cooldown", "aware"), np.float32),
    "goal": (3, ("tx_x", "tz_z", "pause", "reaction"), np.float32),
    "traits": (4, ("speed_factor", "walk_top", "chase_top", "runner"), np.float32),
    "codes": (5, ("state", "action", "health", "kind"), np.int32),
    "looks": (6, ("tint", "head", "weapon", "spawned_step"), np.uint32),
}
SCRATCH_BINDING = 7
AGENT_BYTES = 16 * (len(FIELDS) + 1)  # the state and the scratch (push, offset to the player)


def pack(ai, rows: slice = slice(None)) -> dict[str, np.ndarray]:
    """Each buffer's (N, 4) array from a numpy CrowdAI `ai` (its agents `rows`)."""
    out = {}
    ox, oz = float(ai.origin[0]), float(ai.origin[1])
    n = len(range(*rows.indices(ai.n)))
    for name, (_, columns, dtype) in FIELDS.items():
        block = np.empty((n, 4), dtype)
        for col, field in enumerate(columns):
            if field == "tint":
                block[:, col] = np.ascontiguousarray(ai.tint[rows]).view(np.uint32)[:, 0]
            elif field == "weapon":
                block[:, col] = (ai.weapon[rows].astype(np.int64) + 1).astype(np.uint32)
            elif field.endswith(("_x", "_z")):
                base, axis = field[:-2], field[-1]
                block[:, col] = getattr(ai, base)[rows] - (ox if axis == "x" else oz)
            else:
                block[:, col] = getattr(ai, field)[rows]
        out[name] = block
    return out


def unpack(blocks: dict[str, np.ndarray], origin) -> dict[str, np.ndarray]:
    """The numpy AI's arrays (float64 where it keeps float64, absolute positions) from each buffer's
    (N, 4) array."""
    ox, oz = float(origin[0]), float(origin[1])
    out = {}
    for name, (_, columns, _) in FIELDS.items():
        block = blocks[name]
        for col, field in enumerate(columns):
            column = block[:, col]
            if field == "tint":
                out["tint"] = np.ascontiguousarray(column).view(np.uint8).reshape(-1, 4).copy()
            elif field == "weapon":
                out["weapon"] = column.astype(np.int64).astype(np.int16) - 1
            elif field.endswith(("_x", "_z")):
                base, axis = field[:-2], field[-1]
                out[base] = column.astype(np.float64) + (ox if axis == "x" else oz)
            elif field in ("state", "action", "kind"):
                out[field] = column.astype(np.int8)
            elif field == "health":
                out[field] = column.astype(np.int16)
            elif field == "runner":
                out[field] = column > 0.5
            elif field == "scale":
                out[field] = column.copy()
            elif field in ("head", "spawned_step"):
                out[field] = column.astype(np.int64)
            else:
                out[field] = column.astype(np.float64)
    return out


def kind_table(ai) -> np.ndarray:
    """The Kinds uniform block (std140: six vec4 a character) from a CrowdAI's motions."""
    table = np.zeros((len(ai.motions), 6, 4), np.float32)
    for k, m in enumerate(ai.motions):
        lengths = np.where(np.isfinite(ai._action_length[k]), ai._action_length[k], NEVER)
        table[k, 0] = m.walk_stride, m.run_stride, m.run_speed, m.walk_slowest
        table[k, 1] = m.duration["idle"], m.walk_speed, m.upper_body_mask, m.pivots is not None
        table[k, 2] = lengths
        table[k, 3] = ai._action_clip[k]
        table[k, 4, :3] = [m.clip[role] for role in ACTION_ROLES[1:]]
        table[k, 5, :3] = [m.clip[role] for role in ("idle", "walk", "run")]
    return table


def pivot_table(motions) -> np.ndarray:
    """Every character's Motion.pivots as (x, z, down, 0) rows: character, clip, phase sample (zeros for
    a character without them)."""
    table = np.zeros((len(motions), 3, FOOT_SAMPLES + 1, 4), np.float32)
    for k, m in enumerate(motions):
        if m.pivots is not None:
            table[k, :, :, :3] = m.pivots
    return table
