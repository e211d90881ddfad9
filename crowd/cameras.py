"""The crowd's own views: what a newcomer sees first, the horizon view that shows the horde's scale, and
the overview that frames every agent (the benchmarks' view)."""

from __future__ import annotations

import math

import numpy as np

from .frame import Camera
from .lighting import LIGHTING
from .settings import SETTINGS
from .sim.ai import CrowdAI

# The default camera's neighbourhood of the player in a crowd too big to frame whole, and how far it sees
# then: where the fog (crowd.lighting) has hidden 95 % of what is there, so the crowd fades out rather
# than stopping at the far plane.
VIEW_RADIUS_M = 20.0
FOG_FAR_M = -math.log(0.05) / LIGHTING["u_fog_density"]
# Agents from which a newcomer's first view is the horizon view: below, the horde around the player fills
# the picture; from here, that picture looks the same at any size, and the scale is what there is to see.
HORIZON_AGENTS = 10_000
HORIZON_HEIGHT_M = 60.0  # the horizon view's highest eye: higher, the near zombies are specks too


def view_camera(view: str, ai: CrowdAI, aspect: float, town: bool) -> Camera:
    """The camera of a named view: "player", "horizon", "overview", or "auto" (the horizon view from
    HORIZON_AGENTS agents, else the player's)."""
    if view == "auto":
        view = "horizon" if ai.n >= HORIZON_AGENTS else "player"
    if view == "horizon":
        return horizon_camera(ai, aspect, town)
    if view == "overview":
        return overview_camera(ai, aspect, town)
    if view == "player":
        return default_camera(ai, aspect, town)
    raise ValueError(f"view must be one of {', '.join(SETTINGS['view'].choices)}, got {view!r}")


def default_camera(ai: CrowdAI, aspect: float, town: bool) -> Camera:
    """The player's view: the whole crowd where it fits in VIEW_RADIUS_M (or one agent up close), else
    the player and the horde around it, VIEW_RADIUS_M to each side, receding into the fog (the crowd's
    density does not depend on its size, so the picture does not either). A view of the whole of a big
    crowd showed specks at 10,000 agents and fog or sky at a million."""
    if ai.half_extent <= VIEW_RADIUS_M:
        return overview_camera(ai, aspect, town)
    centre = np.array([ai.player[0], 0.0, ai.player[1]])
    return three_quarter_view(centre, VIEW_RADIUS_M, aspect, FOG_FAR_M, town)


def horizon_camera(ai: CrowdAI, aspect: float, town: bool) -> Camera:
    """The horde's scale: from over its near edge, looking across it to its far side, the fog thinned to
    end there, so the crowd thins into the distance instead of into grey (a bigger horde reaches further
    and holds more in the picture). In a town, from over the roofs into its streets."""
    half = max(ai.half_extent, VIEW_RADIUS_M)
    centre = np.array([ai.origin[0], 0.0, ai.origin[1]])
    height = min(max(12.0, (0.3 if town else 0.12) * half), HORIZON_HEIGHT_M)
    eye = centre + np.array([0.0, height, half + 0.25 * height])  # just outside the near edge: the picture's foot is in the horde
    # Pitched down by atan(1/3) (at most: a smaller horde is looked at from nearer its middle), so the
    # near zombies fill the lower picture and the far side sits high in it, under a band of sky.
    target = eye + np.array([0.0, -height, -min(3.0 * height, 0.55 * half)])
    far_side = float(np.linalg.norm(eye - (centre + np.array([half, 0.0, -half]))))
    return Camera(eye=eye, target=target, aspect=aspect, near=max(0.1, 0.25 * height), far=far_side * 1.05,
                  fog_reach=max(FOG_FAR_M, far_side))


def overview_camera(ai: CrowdAI, aspect: float, town: bool) -> Camera:
    """A three-quarter view that frames the whole crowd (or one agent up close): the benchmarks' view,
    which every agent is in."""
    centre = np.array([ai.origin[0], 0.0, ai.origin[1]])
    return three_quarter_view(centre, max(ai.half_extent, 1.2), aspect, 0.0, town)


def overview_distance(half_extent: float) -> float:
    """How far the overview's eye stands from the crowd's centre (the crowd `half_extent` metres to each side)."""
    return half_extent * 1.5 + 2.5


def three_quarter_view(centre: np.ndarray, extent: float, aspect: float, far: float, town: bool = False) -> Camera:
    """A view of `centre` from up and to one side, `extent` metres around it in the picture. In a town,
    from above the street that runs along z through the centre (the origin is a crossing), looking down
    it: a diagonal view would look at the buildings' walls and roofs, not at the crowd in the streets."""
    dist = overview_distance(extent)
    eye = centre + (np.array([0.0, dist * 0.55, dist * 0.9]) if town else np.array([dist * 0.45, dist * 0.5, dist * 0.85]))
    return Camera(eye=eye, target=centre + np.array([0.0, 0.8, 0.0]), aspect=aspect, far=max(200.0, dist * 4, far))
