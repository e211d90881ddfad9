"""The window's cameras: the orbit camera (orbit, pan and zoom around a target point) and the follow
camera behind the survivor, which the town's buildings stop."""

from __future__ import annotations

import math

import numpy as np

from crowd.frame import Camera


class OrbitControl:
    """Orbit, pan and zoom around a target point, the way editors do: drag to orbit, drag with the
    middle button (or shift) to pan along the ground, scroll to zoom. Writes a frame Camera (crowd.frame)."""

    def __init__(self, camera: Camera):
        eye, target = np.asarray(camera.eye, np.float64), np.asarray(camera.target, np.float64)
        offset = eye - target
        self.target = target.copy()
        self.distance = float(np.linalg.norm(offset))
        self.yaw = math.atan2(offset[0], offset[2])
        self.pitch = math.asin(max(-1.0, min(1.0, offset[1] / max(self.distance, 1e-9))))

    def orbit(self, dx: float, dy: float) -> None:
        """Pixels dragged: 0.3 degrees per pixel; the pitch stays between 3 and 89 degrees."""
        self.yaw -= math.radians(0.3 * dx)
        self.pitch = min(math.radians(89.0), max(math.radians(3.0), self.pitch + math.radians(0.3 * dy)))

    def pan(self, dx: float, dy: float) -> None:
        """Move the target along the ground, a distance proportional to how far the camera is."""
        k = 0.0015 * self.distance
        right = np.array([math.cos(self.yaw), 0.0, -math.sin(self.yaw)])
        forward = np.array([-math.sin(self.yaw), 0.0, -math.cos(self.yaw)])
        self.target += (-dx * right + dy * forward) * k

    def zoom(self, steps: float) -> None:
        self.distance = min(5000.0, max(1.5, self.distance * (0.88 ** steps)))

    def apply(self, camera: Camera) -> None:
        cp = math.cos(self.pitch)
        offset = self.distance * np.array([cp * math.sin(self.yaw), math.sin(self.pitch), cp * math.cos(self.yaw)])
        camera.target = self.target.copy()
        camera.eye = self.target + offset
        camera.far = max(400.0, self.distance * 4.0)


WALL_SAMPLES = 32  # points tested along the line from the survivor to the follow camera
WALL_CLEARANCE = 0.4  # metres the follow camera keeps from a building's wall
MIN_SHARE = 0.05  # of its ground distance: the least the follow camera keeps when a wall is right behind


class FollowControl:
    """A third-person camera behind the survivor: drag turns it around the survivor and tilts it, the
    wheel moves it in and out. Its ground forward is where the survivor faces and W runs."""

    HEIGHT = 1.5  # metres above the survivor's feet it looks at

    def __init__(self, yaw: float = math.pi, distance: float = 5.5, pitch: float = math.radians(22.0)):
        self.yaw = yaw  # the camera sits at (sin yaw, cos yaw) from the survivor, looking back at it
        self.distance = distance
        self.pitch = pitch

    def orbit(self, dx: float, dy: float) -> None:
        self.yaw -= math.radians(0.3 * dx)
        self.pitch = min(math.radians(75.0), max(math.radians(5.0), self.pitch + math.radians(0.3 * dy)))

    def zoom(self, steps: float) -> None:
        self.distance = min(40.0, max(2.0, self.distance * (0.88 ** steps)))

    def forward(self) -> np.ndarray:
        """The camera's forward on the ground (x, z): away from the camera, past the survivor."""
        return np.array([-math.sin(self.yaw), -math.cos(self.yaw)])

    @classmethod
    def walls_in(cls, obstacles):
        """What stops the camera in a town (crowd.asset.town.Obstacles): what stands taller than a metre
        above the survivor's head, so buildings, not cars or barriers. None without a town."""
        return obstacles.taller_than(cls.HEIGHT + 1.0) if obstacles is not None else None

    def apply(self, camera: Camera, survivor_position, walls=None) -> None:
        """Place `camera` behind the survivor. `walls` (crowd.asset.town.Obstacles, the town's buildings):
        where one stands between the survivor and the camera's place, the camera comes in to the last
        point on the survivor's side, WALL_CLEARANCE metres off it, at the same height, instead of looking
        from inside it."""
        target = np.array([survivor_position[0], self.HEIGHT, survivor_position[1]], np.float64)
        cp = math.cos(self.pitch)
        offset = self.distance * np.array([cp * math.sin(self.yaw), math.sin(self.pitch), cp * math.cos(self.yaw)])
        if walls is not None:
            along = np.linspace(0.0, 1.0, WALL_SAMPLES + 1)[1:]  # from the survivor outwards
            clear = walls.distance(target[0] + offset[0] * along, target[2] + offset[2] * along) >= WALL_CLEARANCE
            if not clear.all():
                # The first sample too near a wall: the camera comes in to the one before it, at its height
                # (so it looks down over the survivor's shoulder, never from inside the wall; a sliver of
                # the way out stays, since a view straight down has no up).
                first = int(np.argmin(clear))
                offset[[0, 2]] *= max(along[first - 1] if first else 0.0, MIN_SHARE)
        camera.target = target
        camera.eye = target + offset
        camera.far = 800.0
