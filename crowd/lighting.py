"""The values of shaders/lighting.glsl's uniforms: one sun, sky and ground ambient, fog. A module of its
own so the Panda3D peer (bench/peers_panda.py) lights its actors the same way without importing the
renderer (and pyglm, which the peer's GPU machine does not get)."""

import math

SUN_DIR = tuple(v / math.sqrt(0.45**2 + 0.75**2 + 0.35**2) for v in (0.45, 0.75, 0.35))  # toward the sun
FOG_COLOR = (0.09, 0.1, 0.13)  # linear; the clear colour matches it after the display curve
LIGHTING = {"u_sun_dir": SUN_DIR, "u_sun_color": (1.7, 1.45, 1.1), "u_sky_color": (0.16, 0.2, 0.3),
            "u_ground_color": (0.1, 0.08, 0.06), "u_fog_color": FOG_COLOR, "u_fog_density": 0.004}


def fog_density(reach: float | None) -> float:
    """The exponential fog's density per metre (shaders/lighting.glsl) where it hides 95 % of what is
    `reach` metres away; None: the lighting's own."""
    return float(LIGHTING["u_fog_density"]) if reach is None else -math.log(0.05) / float(reach)
