"""A one-dimensional search the AI and the measuring tools share (crowd.sim.motion.stride_from_feet,
bench.skate_report.worst_speed): golden-section search for the top of a function that rises and then
falls over an interval (unimodal)."""

from __future__ import annotations

import math

_RATIO = (math.sqrt(5.0) - 1.0) / 2.0


def golden_section_max(f, low: float, high: float, rounds: int) -> tuple[float, float]:
    """(x, f(x)) at the largest of the points tried in [low, high] by `rounds` golden-section steps,
    one new evaluation each, for a unimodal `f`."""
    c, d = high - _RATIO * (high - low), low + _RATIO * (high - low)
    fc, fd = f(c), f(d)
    for _ in range(rounds):
        if fc >= fd:
            high, d, fd = d, c, fc
            c = high - _RATIO * (high - low)
            fc = f(c)
        else:
            low, c, fc = c, d, fd
            d = low + _RATIO * (high - low)
            fd = f(d)
    return (c, fc) if fc >= fd else (d, fd)
