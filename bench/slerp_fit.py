"""Fit qt_corrected's nlerp weight (crowd.anim.palette_reference.SLERP_FIT) and print its error against slerp.

The corrected weight is u' = u + u (u - 1/2) (u - 1) (1 - d) (A(d) (u - 1/2)^2 + B(d)), with d the
keys' dot product and A, B quadratics: linear in their six coefficients, so a weighted least-squares
fit to the exact weight (the u' at which nlerp turns by u times the keys' angle) finds them. The rows
are dense near d = 1, where most key intervals are, and weighted by the angle error's size relative to
nlerp's (which grows as the angle cubed), so the fit keeps its ratio to nlerp everywhere.

Run: python -m bench.slerp_fit
"""

from __future__ import annotations

import numpy as np


def exact_weight(u, d):
    """The weight at which nlerp between unit keys with dot product d turns by u times their angle."""
    angle = np.arccos(np.clip(d, -1.0, 1.0))
    a = np.tan(u * angle)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(angle < 1e-9, u, a / (np.sin(angle) + a * (1.0 - np.cos(angle))))


def nlerp_angle(u, d):
    """The angle nlerp at weight u turns by, between keys with dot product d."""
    angle = np.arccos(d)
    return np.arctan2(u * np.sin(angle), 1.0 - u + u * np.cos(angle))


def basis(u, d):
    g = u * (u - 0.5) * (u - 1.0) * (1.0 - d)
    return np.stack([g * (u - 0.5) ** 2 * d ** i for i in range(3)] + [g * d ** j for j in range(3)], -1)


def fit() -> np.ndarray:
    u, d = np.meshgrid(np.linspace(0.0, 1.0, 301), 1.0 - np.geomspace(1e-5, 1.0, 300))
    u, d = u.ravel(), d.ravel()
    target = exact_weight(u, d) - u
    weight = np.sin(np.arccos(d)) / (1.0 - d + 1e-9) ** 1.5
    ok = np.isfinite(target)
    coef, *_ = np.linalg.lstsq((basis(u, d) * weight[:, None])[ok], (target * weight)[ok], rcond=None)
    return coef


def main() -> None:
    coef = fit()
    print("SLERP_FIT =", tuple(round(float(c), 12) for c in coef))
    for d0 in (0.0, 0.3, 0.5, 0.7, 0.9, 0.95, 0.99, 0.999):
        u = np.linspace(0.0, 1.0, 4001)
        d = np.full_like(u, d0)
        fitted = np.abs(nlerp_angle(u + basis(u, d) @ coef, d) - u * np.arccos(d0)).max()
        plain = np.abs(nlerp_angle(u, d) - u * np.arccos(d0)).max()
        print(f"keys {np.degrees(2 * np.arccos(d0)):6.1f} deg apart (d {d0}): corrected {fitted:.2e} rad, nlerp {plain:.2e} rad")


if __name__ == "__main__":
    main()
