"""The one place that makes GL contexts.

Headless (CI, the H100 host, tests): a standalone EGL context, which is Mesa's llvmpipe on a machine
with no GPU and the NVIDIA driver where there is one. With a window, moderngl-window owns the
context and ``window_context()`` picks it up.
"""

from __future__ import annotations

import functools
import os

import moderngl

from .errors import CrowdError
from .resources import SHADER_DIR


class GLStage:
    """A stage that owns GL objects. ``with Stage(...) as stage:`` releases them when the block ends,
    however it ends; a constructor that fails half-way releases what it had made before the error
    goes on. ``release()`` may be called any number of times, and on a half-built stage."""

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        init = cls.__dict__.get("__init__")
        if init is None:
            return

        @functools.wraps(init)
        def guarded(self, *args, **kw):
            try:
                init(self, *args, **kw)
            except BaseException:
                self.release()
                raise

        cls.__init__ = guarded

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def release(self) -> None:
        raise NotImplementedError


class GLObjects:
    """The GL objects one stage made, in the order it made them: released together, newest first, as
    many times as asked. ``add`` returns the object, so a stage writes ``self._objects.add(ctx.buffer(...))``."""

    def __init__(self):
        self._objects: list = []

    def add(self, obj):
        self._objects.append(obj)
        return obj

    def remove(self, obj) -> None:
        """Forget `obj`: its owner releases it now, ahead of the rest."""
        self._objects = [o for o in self._objects if o is not obj]

    def __iter__(self):
        return iter(self._objects)

    def gpu_bytes(self) -> int:
        return gpu_bytes(self._objects)

    def release(self) -> None:
        while self._objects:
            self._objects.pop().release()


class GLUnavailable(CrowdError, RuntimeError):
    """No usable OpenGL context could be made; the message says why in one line."""


GL_LIMITS = {"auto": None, "4.1": 410}  # the "gl" setting's choices: the highest GL version whose features the stages use


def has_uniform(program, name: str) -> bool:
    """Whether `program` has uniform (or block) `name`: a dict look-up (moderngl's ``name in program`` walks
    every member, 2,400 walks a frame when it was written so)."""
    return program.get(name, None) is not None


_CACHED = (int, float, bool, tuple, bytes)  # values compared by ==: a numpy array is written every time


def set_uniforms(program, **values) -> None:
    """Write `program`'s uniforms `values`, leaving out those it lacks (compiled out) and those that hold
    the value last written through here: a frame's constants cost no GL call after their first frame.
    A bytes value is the uniform's raw data (an array's). A uniform set through here must be set only
    through here (the cache would not see another write)."""
    written = getattr(program, "_crowd_written", None)
    if written is None:
        written = program._crowd_written = {}
    for name, value in values.items():
        if type(value) in _CACHED and name in written and type(written[name]) is type(value) and written[name] == value:
            continue
        if has_uniform(program, name):
            if type(value) is bytes:
                program[name].write(value)
            else:
                program[name].value = value
            written[name] = value


def feature_level(ctx, limit: int | None = None) -> int:
    """The GL version whose features the stages built on `ctx` use: the context's own, or `limit` where that
    is lower (the "gl" setting: the path a macOS 4.1 core context takes, forced on a context with more)."""
    return ctx.version_code if limit is None else min(ctx.version_code, int(limit))


def limit_note(ctx, limit: int | None) -> str:
    """What a refusal adds where `limit` lowers the context's version (", used as GL 4.1 (--gl)"), else ""."""
    return "" if limit is None or limit >= ctx.version_code else f", used as GL {limit // 100}.{limit % 100 // 10} (--gl)"


def has_compute(ctx, limit: int | None = None) -> bool:
    """Whether the stages may use compute shaders, storage buffers and image load/store (GL 4.3): the
    compute processor, the GPU cull and the morph deltas' buffers need them; below it (macOS's 4.1, GL 3.3)
    they take the fragment processor, the CPU cull and textures. `limit`: as for ``feature_level``."""
    return feature_level(ctx, limit) >= 430


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
    """Bytes of GPU memory held by the textures, renderbuffers and buffers among `objects` (other
    objects count 0). A texture whose ``extra`` says {"mipmapped": True} counts its chain down to 1x1."""
    total = 0
    for obj in objects:
        if isinstance(obj, (moderngl.Texture, moderngl.TextureArray)):
            w, h = obj.width, obj.height
            texels = w * h
            if isinstance(obj.extra, dict) and obj.extra.get("mipmapped"):
                while w > 1 or h > 1:
                    w, h = max(w // 2, 1), max(h // 2, 1)
                    texels += w * h
            layers = obj.layers if isinstance(obj, moderngl.TextureArray) else 1
            total += texels * layers * obj.components * _DTYPE_BYTES[obj.dtype]
        elif isinstance(obj, moderngl.Renderbuffer):
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
    """Source of shaders/<name> with ``#include "file"`` lines expanded (an included file may include
    others; each file once, so a cycle or a second include of a file adds nothing) and ``#define KEY
    VALUE`` lines inserted after ``#version``: features a scene does not use are compiled out rather
    than branched around."""
    lines = _expand(name, set())
    if not lines or not lines[0].startswith("#version"):
        raise GLUnavailable(f"shader {name} must start with #version")
    extra = [f"#define {key} {value}" for key, value in (defines or {}).items()]
    return "\n".join(lines[:1] + extra + lines[1:]) + "\n"


def _expand(name: str, seen: set) -> list[str]:
    seen.add(name)
    lines = []
    for line in _read_shader(name).splitlines():
        stripped = line.strip()
        if stripped.startswith("#include"):
            included = stripped.split('"')[1]
            if included not in seen:
                lines += _expand(included, seen)
        else:
            lines.append(line)
    return lines


def _read_shader(name: str) -> str:
    path = SHADER_DIR / name
    try:
        return path.read_text()
    except OSError as exc:
        raise GLUnavailable(f"shader {name} not found in {SHADER_DIR}") from exc


def current_context_function(name: str, prototype):
    """A GL entry point of the context current on this thread, through ctypes: eglGetProcAddress for
    EGL contexts (headless), glXGetProcAddressARB for GLX windows, the OpenGL framework's own symbols on
    macOS (whose 4.1 core exports every entry point it has), wglGetProcAddress (or opengl32's own, for
    GL 1.1's) on Windows. For the few calls moderngl lacks (fences, the transform-feedback cull's) and for
    contexts it does not own (the Panda3D peer's glFinish)."""
    import ctypes
    import sys

    if sys.platform in ("darwin", "win32"):
        return _system_gl_function(name, prototype)
    loader = None
    try:
        egl = ctypes.CDLL("libEGL.so.1")
        egl.eglGetCurrentContext.restype = ctypes.c_void_p
        if egl.eglGetCurrentContext():
            egl.eglGetProcAddress.restype = ctypes.c_void_p
            egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
            loader = egl.eglGetProcAddress
    except OSError:
        pass
    if loader is None:
        try:
            glx = ctypes.CDLL("libGL.so.1")
            glx.glXGetCurrentContext.restype = ctypes.c_void_p
            glx.glXGetProcAddressARB.restype = ctypes.c_void_p
            glx.glXGetProcAddressARB.argtypes = [ctypes.c_char_p]
            current = glx.glXGetCurrentContext()
            loader = glx.glXGetProcAddressARB
        except (OSError, AttributeError) as exc:
            raise GLUnavailable(f"no way to load {name}: {exc}") from exc
        if not current:  # a pointer would load, but calling it would do nothing (or crash)
            raise GLUnavailable(f"no GL context is current on this thread to call {name} on")
    address = loader(name.encode())
    if not address:
        raise GLUnavailable(f"the GL context has no {name}")
    return prototype(address)


def _system_gl_function(name: str, prototype):
    """``current_context_function`` on macOS and Windows (not run by CI, which has neither)."""
    import ctypes
    import sys

    try:
        if sys.platform == "darwin":
            framework = ctypes.CDLL("/System/Library/Frameworks/OpenGL.framework/OpenGL")
            framework.CGLGetCurrentContext.restype = ctypes.c_void_p
            if not framework.CGLGetCurrentContext():
                raise GLUnavailable(f"no GL context is current on this thread to call {name} on")
            return prototype((name, framework))
        opengl32 = ctypes.WinDLL("opengl32")
        opengl32.wglGetCurrentContext.restype = ctypes.c_void_p
        if not opengl32.wglGetCurrentContext():
            raise GLUnavailable(f"no GL context is current on this thread to call {name} on")
        opengl32.wglGetProcAddress.restype = ctypes.c_void_p
        opengl32.wglGetProcAddress.argtypes = [ctypes.c_char_p]
        address = opengl32.wglGetProcAddress(name.encode())
        # (wglGetProcAddress answers only past GL 1.1, and some drivers say 1, 2, 3 or -1 for "no"; its
        # pointers are the current context's, and a CFUNCTYPE prototype fits 64-bit Windows' one convention)
        return prototype(address) if address and address not in (1, 2, 3, ctypes.c_void_p(-1).value) else prototype((name, opengl32))
    except (OSError, AttributeError) as exc:
        raise GLUnavailable(f"the GL context has no {name}: {exc}") from exc


def flush_function():
    """glFlush of the current context (hand the queued commands to the GPU without waiting; moderngl
    has only finish). Looked up per owner, as windows (GLX) and headless runs (EGL) load differently."""
    import ctypes

    return current_context_function("glFlush", ctypes.CFUNCTYPE(None))


class Fence:
    """A GL sync object (glFenceSync, core since GL 3.2) that says whether the GPU has finished the
    commands submitted before it. moderngl has no fences, so the entry points come through
    ``current_context_function``; they touch no GL state moderngl caches."""

    _SYNC_GPU_COMMANDS_COMPLETE = 0x9117
    _SYNC_FLUSH_COMMANDS_BIT = 0x1
    _SIGNALED = (0x911A, 0x911C)  # GL_ALREADY_SIGNALED, GL_CONDITION_SATISFIED
    _WAIT_FAILED = 0x911D
    _api = None

    def __init__(self):
        api = Fence._load()
        self._sync = api["glFenceSync"](self._SYNC_GPU_COMMANDS_COMPLETE, 0)
        if not self._sync:
            raise GLUnavailable("glFenceSync returned no sync object")

    @classmethod
    def _load(cls) -> dict:
        if cls._api is None:
            import ctypes

            types = {"glFenceSync": ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_uint, ctypes.c_uint),
                     "glClientWaitSync": ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_void_p, ctypes.c_uint, ctypes.c_uint64),
                     "glDeleteSync": ctypes.CFUNCTYPE(None, ctypes.c_void_p)}
            cls._api = {name: current_context_function(name, proto) for name, proto in types.items()}
        return cls._api

    def signaled(self) -> bool:
        """True when the GPU has finished everything before the fence; never waits."""
        return self._api["glClientWaitSync"](self._sync, 0, 0) in self._SIGNALED

    def wait(self, timeout_s: float = 5.0) -> None:
        """Block until the fence is signaled (flushing first, so it can be)."""
        status = self._api["glClientWaitSync"](self._sync, self._SYNC_FLUSH_COMMANDS_BIT, int(timeout_s * 1e9))
        if status not in self._SIGNALED:
            raise GLUnavailable("a GL fence was not signaled in time" if status != self._WAIT_FAILED else "glClientWaitSync failed")

    def release(self) -> None:
        if self._sync:
            self._api["glDeleteSync"](self._sync)
            self._sync = None


class FencedSlots:
    """Which frame each slot of a read-back ring holds and the fence that says the GPU is done with it:
    a frame's slot is read only once its own copy is done, never while the GPU still writes it."""

    def __init__(self, slots: int):
        self._frames = [-1] * slots
        self._fences: list[Fence | None] = [None] * slots

    def mark(self, frame: int) -> None:
        """Frame `frame`'s commands for its slot are queued: fence them."""
        k = frame % len(self._frames)
        if self._fences[k] is not None:
            self._fences[k].release()
        self._fences[k], self._frames[k] = Fence(), frame

    def ready(self, frame: int) -> bool:
        """Whether frame `frame`'s slot holds that frame, done (never waits)."""
        k = frame % len(self._frames)
        return frame >= 0 and self._frames[k] == frame and self._fences[k] is not None and self._fences[k].signaled()

    def forget(self) -> None:
        self._frames = [-1] * len(self._frames)

    def release(self) -> None:
        for fence in self._fences:
            if fence is not None:
                fence.release()
        self._fences = [None] * len(self._fences)


class Offscreen(GLStage):
    """A colour and depth framebuffer of one size: where headless frames, benchmarks and tests draw."""

    def __init__(self, ctx: moderngl.Context, size: tuple[int, int]):
        self._objects = GLObjects()
        self.framebuffer = None
        self.size = (int(size[0]), int(size[1]))
        color = self._objects.add(ctx.renderbuffer(self.size, 4))
        depth = self._objects.add(ctx.depth_renderbuffer(self.size))
        self.framebuffer = self._objects.add(ctx.framebuffer(color_attachments=[color], depth_attachment=depth))

    def image(self):
        """The colour buffer as (height, width, 3) uint8, top row first."""
        return read_image(self.framebuffer, self.size)

    def release(self) -> None:
        self._objects.release()
        self.framebuffer = None


def read_image(framebuffer: moderngl.Framebuffer, size: tuple[int, int]):
    import numpy as np

    data = framebuffer.read(components=3, alignment=1)
    return np.frombuffer(data, np.uint8).reshape(size[1], size[0], 3)[::-1].copy()


def import_moderngl_window():
    """moderngl_window, imported without the PendingDeprecationWarning its scene camera raises on import
    ("Importing PyGLM via \"import glm\""; moderngl-window 3.1.1 imports glm the old way). Only that
    warning from that module is filtered: ours import ``from pyglm import glm``."""
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Importing PyGLM via \"import glm\"", category=PendingDeprecationWarning,
                                module=r"moderngl_window\.scene\.camera")
        import moderngl_window
        import moderngl_window.scene  # noqa: F401  (the module that raises it, imported here once)
    return moderngl_window
