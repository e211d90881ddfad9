"""The window's camera control: orbit, pan and zoom around a target point."""

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

    def apply(self, camera: Camera, survivor_position) -> None:
        target = np.array([survivor_position[0], self.HEIGHT, survivor_position[1]], np.float64)
        cp = math.cos(self.pitch)
        camera.target = target
        camera.eye = target + self.distance * np.array([cp * math.sin(self.yaw), math.sin(self.pitch), cp * math.cos(self.yaw)])
        camera.far = 800.0
