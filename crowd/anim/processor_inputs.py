"""The processor's error, the choices its settings take (interpolation, path, palette history) and the
checks of what it is given, each refusing in one line."""

from __future__ import annotations

import math

import moderngl
import numpy as np

from ..errors import CrowdError
from ..gl import has_compute, limit_note
from ..settings import DEFAULTS, SETTINGS
from ..spans import min_max, over_spans

# How one layer turns its two (or four) neighbouring baked keys into a local transform, and how layers
# blend (crowd-bench error measures each; docs/BENCHMARKS.md says why the default is the default):
# - dq_lerp: the DQ keys lerped blindly and normalised; layers blended as dual quaternions (DLB);
# - qt_lerp: each key split into rotation and translation; rotations nlerped, translations lerped;
#   layers blended the same way (ozz-animation's blending job, and the float64 reference's semantics);
# - qt_corrected: as qt_lerp, with the nlerp's weight corrected so that it tracks slerp (palette_reference.SLERP_FIT);
# - qt_cubic: as qt_lerp, with Catmull-Rom through four keys instead of the lerp between two.
INTERPOLATIONS = SETTINGS["interpolation"].choices
DEFAULT_INTERPOLATION = DEFAULTS["interpolation"]  # chosen by crowd-bench error: see docs/BENCHMARKS.md
MAX_HISTORY = SETTINGS["readback_latency"].high + 1  # palettes kept: the latest and one per frame of read-back latency


class ProcessorError(CrowdError, ValueError):
    """Bad processor input; the message is one line."""


def resolve_path(ctx: moderngl.Context, path: str, limit: int | None = None) -> str:
    """The processor path "auto" takes on this context: compute where it has GL 4.3 and `limit` (the "gl"
    setting's: crowd.gl.feature_level) lets the stages use it, else fragment. "compute" where they may not: ProcessorError."""
    compute = has_compute(ctx, limit)
    if path == "compute" and not compute:
        raise ProcessorError(f"the compute path needs GL 4.3, this context has {ctx.version_code}{limit_note(ctx, limit)}")
    return ("compute" if compute else "fragment") if path == "auto" else path


def check_motion(motion, agents: int) -> np.ndarray:
    """The foot lock's per-agent motion (N, 4) float32: ground step x, z and front x, z times the scale,
    all finite, the front not 0."""
    if motion is None:
        raise ProcessorError("the foot lock needs each agent's motion (ground step x, z, front x, z times scale) with its layers")
    m = np.ascontiguousarray(motion, np.float32)
    if m.shape != (agents, 4):
        raise ProcessorError(f"agent motion must be ({agents}, 4) (ground step x, z, front x, z times scale), got {np.shape(motion)}")
    # Two reductions where every value is fine (min and max carry NaN and infinities); the row is found only for the message.
    if m.size and not all(math.isfinite(v) for v in min_max(m)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(m), axis=1))[0])
        raise ProcessorError(f"agent motion of agent {bad} is not finite: {m[bad].tolist()}")

    def shortest(lo: int, hi: int) -> float:  # the shortest front's squared length in a span (crowd.spans)
        front = m[lo:hi, 2] * m[lo:hi, 2]
        front += m[lo:hi, 3] * m[lo:hi, 3]
        return float(front.min()) if hi > lo else math.inf

    if len(m) and not min(over_spans(shortest, len(m))) > 1e-24:
        front = m[:, 2] * m[:, 2] + m[:, 3] * m[:, 3]
        bad = int(np.flatnonzero(~(front > 1e-24))[0])
        raise ProcessorError(f"agent {bad} has front {m[bad, 2:].tolist()} times its scale; the foot lock needs one of length > 0")
    return m


def check_interpolation(interpolation) -> str:
    return SETTINGS["interpolation"].check(interpolation, ProcessorError)


def check_history(history) -> int:
    if isinstance(history, bool) or not isinstance(history, (int, np.integer)) or not 1 <= history <= MAX_HISTORY:
        raise ProcessorError(f"palette history must be a whole number from 1 to {MAX_HISTORY}, got {history!r}")
    return int(history)
