"""PNG files, atomically written. No GL imports, so that every process can write one: the Panda3D
peer's worker must not load moderngl beside Panda3D's own GL stack."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from .files import atomic_write_bytes


def png_bytes(image: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buf, format="PNG")
    return buf.getvalue()


def write_png(path: Path, image: np.ndarray) -> None:
    """An (H, W, 3) or (H, W, 4) uint8 image, top row first, to `path` through a temporary file."""
    atomic_write_bytes(Path(path), png_bytes(image))
