"""The Panda3D side of ``crowd-bench peers`` (crowd/peers.py runs it in a child process): one ``Actor``
per agent, offscreen through EGL (``p3headlessgl``), the way a Python developer would build the crowd
with Panda3D.

Traps this module works around, each checked by the pose screenshot crowd/peers.py compares:
- Under EGL, Panda3D's shader generator has no Cg profile: with ``hardware-animated-vertices`` on,
  ``setShaderAuto()`` silently draws every actor in its bind pose. The GPU modes use a hand-written
  GLSL 1.50 shader (shaders/panda_actor.vert.glsl) with ``ShaderAttrib.F_hardware_skinning``.
- panda3d-gltf 1.3.0 puts the ``Character`` at the common ancestor of the skin's joints and the skinned
  mesh nodes, but when the meshes sit at the scene root (as in the built-in zombie) it takes the root
  joint instead: the hips' offset is then applied twice and every pose is wrong. ``panda_ready_gltf``
  writes a copy whose skin also lists the root joint's parent (with its inverse world matrix), which puts
  the Character there. Meshes, skin weights and clips are untouched.
- A model loaded through the model pool is a copy whose skinned meshes outside the Character still point
  at the pooled original's joints, so the model is loaded with ``noCache`` and its meshes reparented
  under the Character before the first ``Actor`` copies it.
"""

from __future__ import annotations

import ctypes
import math
import tempfile
from pathlib import Path

import numpy as np

from .lighting import LIGHTING
from .peers import FRAME_DT, agent_layout

HARDWARE = {"cpu_walk": False, "gpu_walk": True, "gpu_blend2": True}


def panda_ready_gltf(source: Path, target: Path) -> None:
    """Write `source` as a .glb that panda3d-gltf 1.3.0 skins correctly (see the module docstring)."""
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(source))
    gltf.convert_buffers(pygltflib.BufferFormat.BINARYBLOB)
    blob = bytearray(gltf.binary_blob() or b"")
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


def _world_matrix(gltf, parents: dict, node_index: int) -> np.ndarray:
    from .gltf import node_local_matrix

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
        w, h = spec["size"]
        lines = ["load-display p3headlessgl", "window-type offscreen", f"win-size {w} {h}", "audio-library-name null",
                 "sync-video false", "framebuffer-multisample false", "multisamples 0", "notify-level-device fatal",
                 f"hardware-animated-vertices {'true' if self.hardware else 'false'}"]
        loadPrcFileData("crowd-bench peers", "\n".join(lines))  # in one page the first setting of a variable wins

        from direct.actor.Actor import Actor
        from direct.showbase.ShowBase import ShowBase
        from panda3d.core import ClockObject, Filename, PerspectiveLens, Shader, ShaderAttrib

        self._Actor = Actor
        self.base = ShowBase(windowType="offscreen")
        gsg = self.base.win.getGsg()
        self._gl = f"{gsg.getDriverRenderer()}, {gsg.getDriverVersion()}"
        self.clock = ClockObject.getGlobalClock()
        self.clock.setMode(ClockObject.MNonRealTime)  # every frame advances FRAME_DT, as on the crowd side
        self.clock.setFrameRate(1.0 / FRAME_DT)
        self.clock.reset()
        self._tmp = tempfile.TemporaryDirectory()
        ready = Path(self._tmp.name) / "model.glb"
        panda_ready_gltf(Path(spec["model"]), ready)
        model = self.base.loader.loadModel(Filename.fromOsSpecific(str(ready)), noCache=True)
        character = model.find("**/+Character")
        if character.isEmpty():
            raise ValueError(f"Panda3D found no skeleton in {Path(spec['model']).name}")
        for geom in model.findAllMatches("**/+GeomNode"):
            if not character.isAncestorOf(geom):
                geom.wrtReparentTo(character)
        self.template = Actor(model)
        available = self.template.getAnimNames()
        self.walk, self.run = (_panda_clip_name(c, available) for c in spec["clips"])
        for clip in (self.walk, self.run) if self.blend else (self.walk,):
            if clip not in available:
                raise ValueError(f"Panda3D did not load clip {clip!r}; it has {', '.join(available)}")
        self.frames = {c: self.template.getNumFrames(c) for c in (self.walk, self.run)}
        self.triangles_per_agent = sum(prim.getNumFaces() for gn in self.template.findAllMatches("**/+GeomNode")
                                       for geom in gn.node().getGeoms() for prim in geom.getPrimitives())
        joints = len(self.template.getJoints())

        from .gl import load_shader

        defines = {"HARDWARE_SKINNING": 1, "MAX_TRANSFORMS": max(joints + 1, 4)} if self.hardware else {}
        shader = Shader.make(Shader.SL_GLSL, load_shader("panda_actor.vert.glsl", defines), load_shader("skin.frag.glsl"))
        attrib = ShaderAttrib.make(shader)
        if self.hardware:
            attrib = attrib.setFlag(ShaderAttrib.F_hardware_skinning, True)
        self.root = self.base.render.attachNewNode("crowd")
        self.root.setAttrib(attrib)
        for name, value in LIGHTING.items():
            self.root.setShaderInput(name, tuple(float(v) for v in value) if isinstance(value, tuple) else float(value))
        self.lens = PerspectiveLens()
        self.base.cam.node().setLens(self.lens)
        self.base.win.setClearColor((0, 0, 0, 1))
        self.actors: list = []
        self.n = 0
        self._finish = None

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
        w, h = self.spec["size"]
        self.lens.setFov(math.degrees(2 * math.atan(math.tan(math.radians(22.5)) * w / h)), 45.0)
        self.lens.setNearFar(0.1, float(far))
        self.base.cam.setPos(*_zup(eye))
        self.base.cam.lookAt(*_zup(target))
        self.root.setShaderInput("u_eye", _zup(eye))

    def work(self) -> None:
        self.base.graphicsEngine.renderFrame()

    def finish(self) -> None:
        """glFinish on Panda3D's context, so the frame's GPU work is inside the frame's time."""
        if self._finish is None:
            from .gl import current_context_function

            # p3headlessgl leaves its context current on this thread; if it did not, this refuses.
            self._finish = current_context_function("glFinish", ctypes.CFUNCTYPE(None))
        self._finish()

    def row_extra(self) -> dict:
        return {"triangles": self.triangles_per_agent * self.n, "draws": None, "visible": None}

    def save_screenshot(self, path: str) -> None:
        import io

        from PIL import Image

        from .gltf_write import atomic_write_bytes

        tex = self.base.win.getScreenshot()
        image = np.frombuffer(bytes(tex.getRamImageAs("RGB")), np.uint8).reshape(tex.getYSize(), tex.getXSize(), 3)[::-1]
        buf = io.BytesIO()  # crowd.smoke's png_bytes would import the renderer (and pyglm) into this process
        Image.fromarray(np.ascontiguousarray(image)).save(buf, format="PNG")
        atomic_write_bytes(Path(path), buf.getvalue())

    def info(self) -> dict:
        from panda3d.core import PandaSystem

        try:
            from importlib.metadata import version

            gltf_version = version("panda3d-gltf")
        except Exception:  # metadata missing in a --target install
            gltf_version = "?"
        return {"gl": self._gl, "versions": f"panda3d {PandaSystem.getVersionString()}, panda3d-gltf {gltf_version}",
                "pipe": self.base.pipe.getType().getName(), "triangles_per_agent": self.triangles_per_agent,
                "skinning": "GPU (GLSL 1.50, F_hardware_skinning)" if self.hardware else "CPU (Panda3D default)"}

    def release(self) -> None:
        for actor in self.actors:
            actor.cleanup()
        self.template.cleanup()
        self.base.destroy()
        self._tmp.cleanup()
