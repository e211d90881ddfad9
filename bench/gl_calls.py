"""GL calls a frame: every moderngl call that issues GL commands, counted by wrapping moderngl's classes
for the length of a ``with`` block (a measuring tool: the runtime never imports it).

What it counts is moderngl's calls (a draw, a dispatch, a buffer write, a binding, a uniform written, a
barrier, a query begun or ended), each of which is one to a few GL entry points: a lower bound of the
driver's calls, and the figure the Python side's per-frame cost follows."""

from __future__ import annotations

import collections
import contextlib

import _moderngl
import moderngl

# The methods that reach the driver, per class (state queries and Python-side helpers left out).
_METHODS = {
    moderngl.Context: ("memory_barrier", "copy_buffer", "enable", "disable", "enable_only", "clear", "finish", "clear_samplers"),
    moderngl.ComputeShader: ("run", "run_indirect"),
    moderngl.VertexArray: ("render", "render_indirect", "transform", "bind"),
    moderngl.Buffer: ("write", "read", "read_into", "orphan", "clear", "bind_to_storage_buffer", "bind_to_uniform_block", "write_chunks"),
    moderngl.Texture: ("use", "write", "read", "read_into", "bind_to_image", "build_mipmaps"),
    moderngl.TextureArray: ("use", "write", "read", "read_into", "bind_to_image", "build_mipmaps"),
    moderngl.Texture3D: ("use", "write", "read", "read_into", "bind_to_image", "build_mipmaps"),
    moderngl.Framebuffer: ("use", "clear", "read", "read_into"),
    moderngl.Sampler: ("use",),
    moderngl.Query: ("__enter__", "__exit__"),
    _moderngl.Uniform: ("write",),
}


@contextlib.contextmanager
def counting_gl_calls():
    """Within the block, every call of ``_METHODS`` is counted by "Class.method" (a uniform's ``value``
    set goes through its ``write``); yields the Counter. The classes are restored on leaving, exceptions
    included."""
    counts: collections.Counter = collections.Counter()
    saved = []

    def counted(key, function):
        def call(*args, **kwargs):
            counts[key] += 1
            return function(*args, **kwargs)
        return call

    try:
        for cls, names in _METHODS.items():
            for name in names:
                original = cls.__dict__.get(name)
                if original is None:
                    continue
                saved.append((cls, name, original))
                setattr(cls, name, counted(f"{cls.__name__}.{name}", original))
        yield counts
    finally:
        for cls, name, original in reversed(saved):
            setattr(cls, name, original)
