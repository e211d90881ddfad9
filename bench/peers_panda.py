"""The Panda3D side of ``crowd-bench peers`` (bench/peers.py runs it in a child process): one ``Actor``
per agent, offscreen through EGL (``p3headlessgl``), the way a Python developer would build the crowd
with Panda3D.

Traps this module works around, each checked by the pose screenshot bench/peers.py compares:
- Under EGL, Panda3D's shader generator has no Cg profile: with ``hardware-animated-vertices`` on,
  ``setShaderAuto()`` silently draws every actor in its bind pose. The GPU modes use a hand-written
  GLSL 1.50 shader (shaders/bench/panda_actor.vert.glsl) with ``ShaderAttrib.F_hardware_skinning``.
- panda3d-gltf 1.3.0 puts the ``Character`` at the common ancestor of the skin's joints and the skinned
  mesh nodes, but when the meshes sit at the scene root (as in the built-in zombie) it takes the root
  joint instead: the hips' offset is then applied twice and every pose is wrong. ``panda_ready_gltf``
  writes a copy whose skin also lists the root joint's parent (with its inverse world matrix), which puts
  the Character there. Meshes, skin weights and clips are untouched. The copy also keeps only the scene
  it shows (``panda_ready_gltf`` says why).
- panda3d-gltf 1.3.0 reads only dense accessors: a sparse one (the built-in zombie's morph targets are
  sparse, with no bufferView) stops its converter with ``KeyError: 'bufferView'``. The copy leaves the
  morph targets out, and their weight channels with them (the crowd side draws none in this benchmark
  either: the comparison stays skinning against skinning), and writes any other sparse accessor dense.
- A model loaded through the model pool is a copy whose skinned meshes outside the Character still point
  at the pooled original's joints, so the model is loaded with ``noCache`` and its meshes reparented
  under the Character before the first ``Actor`` copies it.

The LOD modes build the Actor the way Panda3D's manual does it: one model per LOD level (here one copy
of the glTF per level, whose scene holds that level's meshes), ``setLODNode`` and ``addLOD`` at the
crowd's distances, and ``mergeLODBundles`` (Panda3D's default), so that the levels share one skeleton
and each actor is animated once whichever level it shows.
"""

from __future__ import annotations

import ctypes
import math
import tempfile
from pathlib import Path

import numpy as np

from crowd.draw.frame_block import lighting_vectors
from crowd.lighting import LIGHTING
from .peer_work import FRAME_DT, agent_layout

HARDWARE = {"cpu_walk": False, "gpu_walk": True, "gpu_blend2": True, "cpu_walk_lod": False, "gpu_walk_lod": True,
            "gpu_walk_threaded": True}
# Panda3D's own answer to a CPU-bound frame: App, Cull (where Actors animate) and Draw on three threads,
# each a frame behind the one before it.
THREADED = {"gpu_walk_threaded"}
LAST_LOD_OUT_M = 1e7  # the last level's far switch distance: it shows at any distance beyond the others


def lod_levels(source: Path) -> list[int]:
    """The LOD levels (0, 1, ...) at which every skinned piece the glTF scene shows has a mesh. The
    meshes carry ``extras.crowd.piece`` and ``lod`` (crowd/asset/gltf_write.py writes them); a model without
    them has the one level [0]."""
    import pygltflib

    return _scene_lods(pygltflib.GLTF2().load(str(source)))[1]


def _scene_lods(gltf) -> tuple[dict, list[int]]:
    """(piece, lod) → node for every mesh node with crowd extras, and the complete levels of the scene."""
    from crowd.asset.gltf.reader import crowd_extras

    by_piece = {}
    for i, node in enumerate(gltf.nodes):
        extras = crowd_extras(gltf.meshes[node.mesh]) if node.mesh is not None else {}
        if "piece" in extras:
            by_piece[(str(extras["piece"]), int(extras.get("lod", 0)))] = i
    shown = [piece for (piece, lod), i in by_piece.items() if i in gltf.scenes[gltf.scene or 0].nodes]
    levels = [0]
    while shown and all((piece, levels[-1] + 1) in by_piece for piece in shown):
        levels.append(levels[-1] + 1)
    return by_piece, levels


def panda_ready_gltf(source: Path, target: Path, lod: int = 0) -> None:
    """Write `source` as a .glb that panda3d-gltf 1.3.0 skins correctly (see the module docstring),
    whose scene shows the pieces at LOD `lod` in place of those it shows (``lod_levels`` lists the levels)."""
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(source))
    by_piece, levels = _scene_lods(gltf)
    if lod not in levels:
        raise ValueError(f"{Path(source).name} has no complete LOD {lod}; its levels are {levels}")
    node_piece = {i: piece for (piece, _), i in by_piece.items()}
    scene = gltf.scenes[gltf.scene or 0]
    scene.nodes = [by_piece[(node_piece[i], lod)] if i in node_piece else i for i in scene.nodes]
    # panda3d-gltf builds every scene and shares a mesh's GeomNode between them: a mesh that two scenes
    # show (the zombie's "lod1" scene, say) ends up skinned to the last one's Character. Keep one scene.
    gltf.scenes, gltf.scene = [scene], 0
    gltf.convert_buffers(pygltflib.BufferFormat.BINARYBLOB)
    blob = bytearray(gltf.binary_blob() or b"")
    _leave_out_morph_targets(gltf)
    _write_sparse_dense(gltf, blob)
    parents = {child: i for i, node in enumerate(gltf.nodes) for child in (node.children or [])}
    for skin in gltf.skins:
        joints = set(skin.joints)
        roots = [j for j in skin.joints if parents.get(j) not in joints]
        parent = parents.get(roots[0]) if len(roots) == 1 else None
        if parent is None or parent in joints:
            continue  # no single root joint under a plain node: nothing to anchor the Character to
        count = len(skin.joints)
        if skin.inverseBindMatrices is None:
            ibm = np.tile(np.eye(4, dtype=np.float32).reshape(1, 16), (count, 1))
        else:
            acc = gltf.accessors[skin.inverseBindMatrices]
            view = gltf.bufferViews[acc.bufferView]
            start = (view.byteOffset or 0) + (acc.byteOffset or 0)
            ibm = np.frombuffer(bytes(blob[start:start + count * 64]), np.float32).reshape(count, 16)
        inverse_world = np.linalg.inv(_world_matrix(gltf, parents, parent)).T.astype(np.float32)  # column-major
        matrices = np.concatenate([ibm, inverse_world.reshape(1, 16)])
        blob.extend(b"\0" * (-len(blob) % 4))
        gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(blob), byteLength=matrices.nbytes))
        blob.extend(matrices.tobytes())
        gltf.accessors.append(pygltflib.Accessor(bufferView=len(gltf.bufferViews) - 1, componentType=pygltflib.FLOAT,
                                                 count=len(matrices), type=pygltflib.MAT4))
        skin.inverseBindMatrices = len(gltf.accessors) - 1
        skin.joints = list(skin.joints) + [parent]
    gltf.buffers[0].byteLength = len(blob)
    gltf.set_binary_blob(bytes(blob))
    gltf.save_binary(str(target))


def _leave_out_morph_targets(gltf) -> None:
    """No primitive keeps its targets, no mesh its default weights, no animation its weight channels."""
    for mesh in gltf.meshes:
        mesh.weights = None
        if isinstance(mesh.extras, dict):
            mesh.extras.pop("targetNames", None)
        for primitive in mesh.primitives:
            primitive.targets = None
    for animation in gltf.animations:
        animation.channels = [c for c in animation.channels if c.target.path != "weights"]


_COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def _read_view(gltf, blob: bytearray, view_index: int, offset: int, count: int, dtype, width: int) -> np.ndarray:
    """(count, width) elements of a bufferView from `offset`, honouring its byteStride."""
    view = gltf.bufferViews[view_index]
    item = np.dtype(dtype).itemsize * width
    stride = view.byteStride or item
    start = (view.byteOffset or 0) + offset
    rows = [bytes(blob[start + i * stride:start + i * stride + item]) for i in range(count)] if stride != item else None
    data = b"".join(rows) if rows is not None else bytes(blob[start:start + count * item])
    return np.frombuffer(data, dtype).reshape(count, width).copy()


def _write_sparse_dense(gltf, blob: bytearray) -> None:
    """Every referenced-or-not sparse accessor (and one without a bufferView: zeros) written out dense."""
    import pygltflib

    for acc in gltf.accessors:
        if acc.sparse is None and acc.bufferView is not None:
            continue
        dtype, width = _COMPONENTS[acc.componentType], _WIDTH[acc.type]
        if acc.bufferView is None:
            values = np.zeros((acc.count, width), dtype)
        else:
            values = _read_view(gltf, blob, acc.bufferView, acc.byteOffset or 0, acc.count, dtype, width)
        if acc.sparse is not None:
            s = acc.sparse
            where = _read_view(gltf, blob, s.indices.bufferView, s.indices.byteOffset or 0, s.count, _COMPONENTS[s.indices.componentType], 1)
            values[where[:, 0].astype(np.int64)] = _read_view(gltf, blob, s.values.bufferView, s.values.byteOffset or 0, s.count, dtype, width)
        blob.extend(b"\0" * (-len(blob) % 4))
        gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(blob), byteLength=values.nbytes))
        blob.extend(values.tobytes())
        acc.bufferView, acc.byteOffset, acc.sparse = len(gltf.bufferViews) - 1, 0, None


def _world_matrix(gltf, parents: dict, node_index: int) -> np.ndarray:
    from crowd.asset.gltf.tree import node_local_matrix

    m = np.eye(4)
    i = node_index
    while i is not None:
        m = node_local_matrix(gltf.nodes[i]) @ m
        i = parents.get(i)
    return m


def _panda_clip_name(name: str, available: list[str]) -> str:
    """Our importer names an unnamed glTF animation i "clip<i>", panda3d-gltf names it "anim<i>"."""
    if name not in available and name.startswith("clip") and name[4:].isdigit() and f"anim{name[4:]}" in available:
        return f"anim{name[4:]}"
    return name


def _triangles(model) -> int:
    return sum(prim.getNumFaces() for gn in model.findAllMatches("**/+GeomNode")
               for geom in gn.node().getGeoms() for prim in geom.getPrimitives())


def _zup(v) -> tuple:
    """A Y-up point (ours, glTF's) in Panda3D's Z-up world: panda3d-gltf maps (x, y, z) to (x, -z, y)."""
    return (float(v[0]), float(-v[2]), float(v[1]))


class PandaSide:
    def __init__(self, spec: dict):
        from panda3d.core import loadPrcFileData

        self.spec = spec
        self.mode = spec["mode"]
        if self.mode not in HARDWARE:
            raise ValueError(f"unknown Panda3D mode {self.mode!r}")
        self.hardware = HARDWARE[self.mode]
        self.blend = self.mode.endswith("blend2")
        self.lod = self.mode.endswith("_lod")
        self.threaded = self.mode in THREADED
        w, h = spec["size"]
        lines = ["load-display p3headlessgl", "window-type offscreen", f"win-size {w} {h}", "audio-library-name null",
                 "sync-video false", "framebuffer-multisample false", "multisamples 0", "notify-level-device fatal",
                 f"hardware-animated-vertices {'true' if self.hardware else 'false'}"]
        if self.threaded:
            lines.append("threading-model Cull/Draw")
        loadPrcFileData("crowd-bench peers", "\n".join(lines))  # in one page the first setting of a variable wins

        from direct.actor.Actor import Actor
        from direct.showbase.ShowBase import ShowBase
        from panda3d.core import ClockObject, Filename, PerspectiveLens, Shader, ShaderAttrib

        self._Actor = Actor
        self.base = ShowBase(windowType="offscreen")
        if self.threaded:
            self._reopen_with_desktop_gl()
        self.clock = ClockObject.getGlobalClock()
        self.clock.setMode(ClockObject.MNonRealTime)  # every frame advances FRAME_DT, as on the crowd side
        self.clock.setFrameRate(1.0 / FRAME_DT)
        self.clock.reset()
        self._tmp = tempfile.TemporaryDirectory()
        source = Path(spec["model"])
        # The crowd clamps to its last level beyond the last distance, so more levels than distances + 1 are never shown.
        levels = lod_levels(source)[:len(spec["lod_distances"]) + 1] if self.lod else [0]
        models = []
        for level in levels:
            ready = Path(self._tmp.name) / f"lod{level}.glb"
            panda_ready_gltf(source, ready, level)
            model = self.base.loader.loadModel(Filename.fromOsSpecific(str(ready)), noCache=True)
            character = model.find("**/+Character")
            if character.isEmpty():
                raise ValueError(f"Panda3D found no skeleton in {source.name}")
            for geom in model.findAllMatches("**/+GeomNode"):
                if not character.isAncestorOf(geom):
                    geom.wrtReparentTo(character)
            models.append(model)
        self.triangles_per_level = [_triangles(m) for m in models]
        if len(models) == 1:
            self.template = Actor(models[0])
        else:
            self.template = Actor()
            self.template.setLODNode()
            switches = [0.0, *(float(d) for d in spec["lod_distances"][:len(levels) - 1]), LAST_LOD_OUT_M]
            for level in levels:  # Panda3D's switch: shown from `out` (near) to `in` (far)
                self.template.addLOD(str(level), inDist=switches[level + 1], outDist=switches[level])
            # The crowd measures LOD distance to the centre of the bind-pose box; so does this LODNode.
            low, high = models[0].getTightBounds()
            self.lod_center = (low + high) * 0.5
            for level, model in zip(levels, models):
                # The first level binds the clips; the others merge into its skeleton (mergeLODBundles).
                self.template.loadModel(model, lodName=str(level), copy=False, autoBindAnims=level == 0)
            self.template.setCenter(self.lod_center)
        self.lod_switches = [self.template.switches[str(level)] for level in levels] if len(levels) > 1 else None
        available = self.template.getAnimNames()
        self.walk, self.run = (_panda_clip_name(c, available) for c in spec["clips"])
        for clip in (self.walk, self.run) if self.blend else (self.walk,):
            if clip not in available:
                raise ValueError(f"Panda3D did not load clip {clip!r}; it has {', '.join(available)}")
        self.frames = {c: self.template.getNumFrames(c) for c in (self.walk, self.run)}
        self.triangles_per_agent = self.triangles_per_level[0]
        joints = len(self.template.getJoints())

        from crowd.gl import load_shader

        defines = {"HARDWARE_SKINNING": 1, "MAX_TRANSFORMS": max(joints + 1, 4)} if self.hardware else {}
        shader = Shader.make(Shader.SL_GLSL, load_shader("bench/panda_actor.vert.glsl", defines), load_shader("skin.frag.glsl", {"FRAME_UNIFORMS": 1}))
        attrib = ShaderAttrib.make(shader)
        if self.hardware:
            attrib = attrib.setFlag(ShaderAttrib.F_hardware_skinning, True)
        self.root = self.base.render.attachNewNode("crowd")
        self.root.setAttrib(attrib)
        for name, value in lighting_vectors(LIGHTING["u_fog_density"]).items():  # (skin.frag.glsl's lighting, as plain uniforms)
            self.root.setShaderInput(name, tuple(float(v) for v in value))
        self.lens = PerspectiveLens()
        self.base.cam.node().setLens(self.lens)
        self.base.win.setClearColor((0, 0, 0, 1))
        self.actors: list = []
        self.n = self.triangles = 0
        self._finish = None

    def _reopen_with_desktop_gl(self) -> None:
        """p3headlessgl binds EGL's desktop-GL API (eglBindAPI) on the thread that makes the pipe, but the
        API is per thread: threaded, the draw thread makes the context under EGL's default, OpenGL ES
        1.1, where no shader runs and every actor is drawn in its bind pose. Bind it on the draw thread
        (from a draw callback) and open the window again, so that its context is desktop GL."""
        from panda3d.core import PythonCallbackObject

        egl = ctypes.CDLL("libEGL.so.1")
        egl.eglBindAPI.argtypes, egl.eglBindAPI.restype = [ctypes.c_uint], ctypes.c_uint
        bound = []

        def bind_desktop_gl(data):
            bound.append(egl.eglBindAPI(0x30A2))  # EGL_OPENGL_API
            data.upcall()

        for i in range(self.base.win.getNumDisplayRegions()):
            self.base.win.getDisplayRegion(i).setDrawCallback(PythonCallbackObject(bind_desktop_gl))
        for _ in range(8):  # the pipeline draws a frame one or two renderFrame calls after starting it
            if bound:
                break
            # Not syncFrame: it holds the GIL while it waits for the draw thread, which needs it for the callback.
            self.base.graphicsEngine.renderFrame()
        for i in range(self.base.win.getNumDisplayRegions()):
            self.base.win.getDisplayRegion(i).clearDrawCallback()
        for _ in range(3):  # let the frames in flight, which may still call back, finish before closing
            self.base.graphicsEngine.renderFrame()
        if not bound or not bound[0]:
            raise RuntimeError("could not bind desktop GL on Panda3D's draw thread")
        self.base.closeWindow(self.base.win)
        self.base.openDefaultWindow(type="offscreen")
        self.base.graphicsEngine.renderFrame()
        self.base.graphicsEngine.syncFrame()
        version = self.base.win.getGsg().getDriverVersion()
        if "OpenGL ES" in version:
            raise RuntimeError(f"Panda3D's draw thread still has {version}")

    def set_agents(self, n: int) -> None:
        pos, yaw, phase, weight, (eye, target, far) = agent_layout(n, self.spec["seed"])
        while len(self.actors) < n:
            self.actors.append(self._Actor(other=self.template))
        for i, actor in enumerate(self.actors):
            if i >= n:
                actor.detachNode()  # not traversed: neither animated nor drawn
                continue
            actor.reparentTo(self.root)
            actor.setPos(*_zup(pos[i]))
            actor.setH(math.degrees(yaw[i]))
            if self.blend:
                actor.enableBlend()
                actor.setControlEffect(self.walk, float(weight[i]))
                actor.setControlEffect(self.run, float(1.0 - weight[i]))
                clips = (self.walk, self.run)
            else:
                clips = (self.walk,)
            for clip in clips:  # start each clip at the agent's phase, then loop from there
                actor.pose(clip, float(phase[i]) * self.frames[clip])
                actor.loop(clip, restart=0)
        self.n = n
        self.triangles = self.triangles_per_agent * n
        if self.lod_switches:  # the level Panda3D's LODNode shows each agent (heading left out: the centre is near the axis)
            centers = np.array([_zup(p) for p in pos]).reshape(n, 3) + np.array(self.lod_center)[None]
            dist = np.linalg.norm(centers - np.array(_zup(eye))[None], axis=1)
            level = np.searchsorted([far for far, _ in self.lod_switches[:-1]], dist, side="right")
            self.triangles = int(np.take(self.triangles_per_level, level).sum())
        w, h = self.spec["size"]
        self.lens.setFov(math.degrees(2 * math.atan(math.tan(math.radians(22.5)) * w / h)), 45.0)
        self.lens.setNearFar(0.1, float(far))
        self.base.cam.setPos(*_zup(eye))
        self.base.cam.lookAt(*_zup(target))
        self.root.setShaderInput("u_eye", _zup(eye))

    def work(self) -> None:
        self.base.graphicsEngine.renderFrame()

    def finish(self) -> None:
        """glFinish on Panda3D's context, so the frame's GPU work is inside the frame's time. Threaded,
        the context lives on the draw thread and renderFrame waits for the frame before it: the time
        from one renderFrame to the next is then the pipeline's period, which is what a budget asks of it."""
        if self.threaded:
            return
        if self._finish is None:
            from crowd.gl import current_context_function

            # p3headlessgl leaves its context current on this thread; if it did not, this refuses.
            self._finish = current_context_function("glFinish", ctypes.CFUNCTYPE(None))
        self._finish()

    def row_extra(self) -> dict:
        return {"triangles": self.triangles, "draws": None, "visible": None}

    def save_screenshot(self, path: str) -> None:
        from crowd.images import write_png

        self.base.graphicsEngine.syncFrame()  # threaded, the last frame may still be drawing
        tex = self.base.win.getScreenshot()
        image = np.frombuffer(bytes(tex.getRamImageAs("RGB")), np.uint8).reshape(tex.getYSize(), tex.getXSize(), 3)[::-1]
        write_png(path, image)

    def info(self) -> dict:
        from panda3d.core import PandaSystem

        try:
            from importlib.metadata import version

            gltf_version = version("panda3d-gltf")
        except Exception:  # metadata missing in a --target install
            gltf_version = "?"
        gsg = self.base.win.getGsg()  # asked after frames were drawn: threaded, the draw thread sets it up
        return {"gl": f"{gsg.getDriverRenderer()}, {gsg.getDriverVersion()}",
                "versions": f"panda3d {PandaSystem.getVersionString()}, panda3d-gltf {gltf_version}",
                "pipe": self.base.pipe.getType().getName(), "triangles_per_agent": self.triangles_per_agent,
                "triangles_per_level": self.triangles_per_level, "lod_switches": self.lod_switches,
                "skinning": "GPU (GLSL 1.50, F_hardware_skinning)" if self.hardware else "CPU (Panda3D default)"}

    def release(self) -> None:
        for actor in self.actors:
            actor.cleanup()
        self.template.cleanup()
        self.base.destroy()
        self._tmp.cleanup()
