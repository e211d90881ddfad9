"""PNG files and animated clips (WebP or GIF), atomically written. No GL imports, so that every process can write one: the Panda3D
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


ANIMATIONS = (".webp", ".gif")


def write_animation(path: Path, frames: list[np.ndarray], fps: float) -> int:
    """(H, W, 3) uint8 frames as an animated WebP (lossy, quality 70) or GIF (a palette per frame), by
    `path`'s suffix, through a temporary file; returns its bytes."""
    from PIL import Image

    path = Path(path)
    if path.suffix.lower() not in ANIMATIONS:
        raise ValueError(f"{path}: a clip is written as {' or '.join(ANIMATIONS)}")
    if not frames:
        raise ValueError(f"{path}: a clip needs at least one frame")
    images = [Image.fromarray(np.ascontiguousarray(f[..., :3])) for f in frames]
    buf = io.BytesIO()
    options = {"quality": 70, "method": 6} if path.suffix.lower() == ".webp" else {"optimize": True}
    images[0].save(buf, format=path.suffix[1:].upper(), save_all=True, append_images=images[1:], duration=round(1000.0 / fps),
                   loop=0, **options)
    atomic_write_bytes(path, buf.getvalue())
    return len(buf.getvalue())
