"""The one place that makes GL contexts.

Headless (CI, the H100 host, tests): a standalone EGL context, which is Mesa's llvmpipe on a machine
with no GPU and the NVIDIA driver where there is one. With a window, moderngl-window owns the
context and ``window_context()`` picks it up.
"""

from __future__ import annotations

import os
from pathlib import Path

import moderngl

SHADER_DIR = Path(__file__).resolve().parent.parent / "shaders"


class GLUnavailable(RuntimeError):
    """No usable OpenGL context could be made; the message says why in one line."""


def has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def headless_context(require: int | None = None) -> moderngl.Context:
    """A standalone EGL context with at least GL `require` (330, 430, ...). With no requirement, the
    best of 4.3 and 3.3: EGL drivers hand out exactly the version asked for (NVIDIA gives 3.3 to a
    3.3 request), so asking for 3.3 alone would hide the compute path."""
    if require is None:
        try:
            return headless_context(430)
        except GLUnavailable:
            return headless_context(330)
    try:
        ctx = moderngl.create_context(standalone=True, backend="egl", require=require)
    except Exception as exc:  # moderngl raises plain Exception subclasses with multi-line text
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise GLUnavailable(f"no EGL context with GL {require // 100}.{require % 100 // 10}: {first}") from exc
    return ctx


def window_context() -> moderngl.Context:
    """The context of the current window (made current by moderngl-window)."""
    return moderngl.create_context()


_DTYPE_BYTES = {"f1": 1, "u1": 1, "f2": 2, "u2": 2, "i2": 2, "f4": 4, "u4": 4, "i4": 4}


def gpu_bytes(objects) -> int:
    """Bytes of GPU memory held by the textures and buffers among `objects` (other objects count 0)."""
    total = 0
    for obj in objects:
        if isinstance(obj, moderngl.Texture):
            total += obj.width * obj.height * obj.components * _DTYPE_BYTES[obj.dtype]
        elif isinstance(obj, moderngl.Buffer):
            total += obj.size
    return total


def describe(ctx: moderngl.Context) -> dict:
    return {
        "gl_renderer": ctx.info.get("GL_RENDERER", "?"),
        "gl_vendor": ctx.info.get("GL_VENDOR", "?"),
        "gl_version": ctx.info.get("GL_VERSION", "?"),
        "version_code": ctx.version_code,
    }


def load_shader(name: str, defines: dict | None = None) -> str:
    """Source of shaders/<name> with ``#include "file"`` lines expanded (one level is all we use) and
    ``#define KEY VALUE`` lines inserted after ``#version``: features a scene does not use are compiled
    out rather than branched around."""
    text = _read_shader(name)
    lines = []
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("#include"):
            lines.append(_read_shader(stripped.split('"')[1]))
        else:
            lines.append(line)
    if not lines or not lines[0].startswith("#version"):
        raise GLUnavailable(f"shader {name} must start with #version")
    extra = [f"#define {key} {value}" for key, value in (defines or {}).items()]
    return "\n".join(lines[:1] + extra + lines[1:]) + "\n"


def _read_shader(name: str) -> str:
    path = SHADER_DIR / name
    try:
        return path.read_text()
    except OSError as exc:
        raise GLUnavailable(f"shader {name} not found in {SHADER_DIR}") from exc
