"""What every benchmark shares: the host's description, the grid crowd and random processor input.
numpy only at import time, so the Panda3D peer (which must not import moderngl) can use it too."""

from __future__ import annotations

import math
import platform

import numpy as np


def device_cpu() -> str:
    import numpy

    return f"{platform.processor() or platform.machine()} ({platform.system()}), Python {platform.python_version()}, numpy {numpy.__version__}"


def grid_layout(n: int):
    """The benchmarks' crowd: n agents 1.5 m apart on a square grid (Y up), and a camera that sees all of
    them. Returns (float64 positions (n, 3), eye, target, far); numpy only, so the Panda3D peer can use it."""
    side = math.ceil(math.sqrt(n))
    pos = np.zeros((n, 3))
    pos[:, 0] = (np.arange(n) % side - side / 2) * 1.5
    pos[:, 2] = (np.arange(n) // side - side / 2) * 1.5
    extent = side * 1.5 / 2
    return pos, np.array([0.0, extent * 1.6 + 3, extent * 1.6 + 5]), np.zeros(3), extent * 8 + 50


def grid_crowd(n: int, aspect: float):
    """``grid_layout`` with the camera as a crowd.frame.Camera. Returns (float64 positions (n, 3), Camera)."""
    from crowd.frame import Camera

    pos, eye, target, far = grid_layout(n)
    return pos, Camera(eye=eye, target=target, aspect=aspect, far=far)


def random_layers(n: int, layer_count: int, clip_count: int, rng: np.random.Generator) -> np.ndarray:
    """Processor input with random clips, phases and weights (0.1 to 1) on every layer."""
    from crowd.frame import CLIP, PHASE, WEIGHT, empty_layers

    layers = empty_layers(n, layer_count)
    layers[..., CLIP] = rng.integers(0, clip_count, (n, layer_count))
    layers[..., PHASE] = rng.uniform(0, 1, (n, layer_count))
    layers[..., WEIGHT] = rng.uniform(0.1, 1.0, (n, layer_count))
    return layers
