"""Attach stage: weapons placed on the CPU from read-back socket matrices, drawn one instanced draw per
(weapon, LOD) mesh. A weapon is drawn at its agent's LOD (the prop's coarsest where it has fewer), and
its shadow one LOD coarser, as the body's is.

Contract: ``attach(read, agents_frame, weapon_of_agent)``:
- ``read`` (readback.SocketRead): socket skinning-matrix rows of some frame's armed agents;
- ``agents_frame`` (AgentFrames): each agent's transform exactly as the crowd's vertex shader applies
  it this frame: camera-relative position, uniform scale, and the heading's cos and sin as the snorm16
  values the instance record carries, so weapon and hand go through the same numbers;
- ``weapon_of_agent``: (N,) weapon index per agent (-1: unarmed).

Per entry: weapon model = agent x (socket skinning matrix x socket bind) x inverse(grip), in float64,
vectorised; uploaded as float32 camera-relative 3x4 rows. An entry whose agent is unarmed now, or
out of range, is dropped without touching the others. ``drawn`` keeps what was uploaded (agents,
weapon indices, rows) so that the error of the frame as drawn can be measured.

Culling: on the CPU cull path ``attach`` is given the visible set and uploads only those weapons. On the
GPU path (``gpu_cull``) the CPU does not know it: every armed agent's weapon is uploaded with its
owner, and a compute pass (shaders/weapon_cull.comp.glsl) keeps those whose agent the body cull marked
visible, compacted per (weapon, LOD) mesh and counted in indirect commands, so a weapon is drawn exactly
when its agent is, at its agent's LOD. With shadows on, each shadow cascade's tile gets the weapons of
the agents in that cascade's volume (the body cull's shadow lists), from lists of their own on both paths. ``last["weapons"]`` counts the weapons placed, ``last["drawn"]`` those drawn (on the GPU
path as the GPU hands the counts back, a frame or two late; ``refresh_counts(wait=True)`` at a run's end).
"""

from __future__ import annotations

import moderngl
import numpy as np

from ..gl import GLObjects, GLStage, load_shader
from .gpu_cull import BUFFER_UPDATE, COMMAND, COMMAND_DTYPE, GROUP_SIZE, VERTEX_ATTRIB_ARRAY, CountRing
from ..asset.model import Character, RigidMesh
from ..asset.vertex_cache import best_triangle_order
from .render import gl_bytes, heading_snorm16, pack_colors, pack_normals
from .shadows import CASCADES

VERTEX_DTYPE = np.dtype([("position", "<f4", 3), ("packed", "<u4", 2)])
INSTANCE_DTYPE = np.dtype([("rows", "<f4", (3, 4))])


class WeaponError(ValueError):
    """Bad weapon input; the message is one line."""


class AgentFrames:
    """Agent transforms as the crowd's vertex shader applies them (see skin.vert.glsl): the position
    relative to the camera in float32, the float32 scale, and the heading's cos and sin as the snorm16
    values of the instance record. Computed only for the agents asked about, so unarmed agents cost
    nothing here."""

    def __init__(self, positions: np.ndarray, yaw: np.ndarray, scale: np.ndarray, eye):
        self._position = np.asarray(positions, np.float64)
        self._yaw = np.asarray(yaw, np.float32)
        self._scale = np.asarray(scale, np.float32)
        self._eye = np.asarray(eye, np.float64)

    def of(self, agents: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(position float32 (M, 3), scale float64 (M,), cos_sin float64 (M, 2)) of those agents."""
        rel = (self._position[agents] - self._eye[None]).astype(np.float32)
        yaw = self._yaw[agents]
        cs = heading_snorm16(yaw)
        return rel, self._scale[agents].astype(np.float64), cs.astype(np.float64) / 32767.0

    def points(self, agents: np.ndarray, model_points: np.ndarray) -> np.ndarray:
        """(M, 3) float64: model-space points of those agents placed as the shader places them:
        x' = position + scale * heading(x), the heading turning +Z toward (sin, cos)."""
        rel, k, cs = self.of(agents)
        p = np.asarray(model_points, np.float64)
        c, s = cs[:, 0], cs[:, 1]
        return rel + k[:, None] * np.stack([c * p[:, 0] + s * p[:, 2], p[:, 1], c * p[:, 2] - s * p[:, 0]], axis=1)


def pack_rigid(mesh: RigidMesh) -> np.ndarray:
    v = np.zeros(len(mesh.positions), VERTEX_DTYPE)
    v["position"] = mesh.positions
    v["packed"][:, 0] = pack_normals(mesh.normals)
    v["packed"][:, 1] = pack_colors(mesh.colors, mesh.base_color, len(v))
    return v


class WeaponRenderer(GLStage):
    """Owns the weapon meshes, their instance buffers and programs."""

    def __init__(self, ctx: moderngl.Context, character: Character, shadows: bool, gpu_cull: bool = False):
        self._objects = GLObjects()
        self._meshes = []
        if not character.props or not character.sockets:
            raise WeaponError(f"character {character.name!r} has no weapons to hold (props and a socket joint are both needed)")
        self.ctx = ctx
        self.names = list(character.props)
        self.socket_joint = int(next(iter(character.sockets.values())))
        bind = np.linalg.inv(np.asarray(character.skeleton.inverse_bind, np.float64))
        self.socket_bind = bind[self.socket_joint]  # the socket joint's model matrix at bind
        self.inverse_grip = np.stack([np.linalg.inv(np.asarray(p.grip, np.float64)) for p in character.props.values()])
        # Per weapon mesh: the socket's skinning matrix times this gives the weapon in model space.
        self._socket_to_weapon = np.stack([self.socket_bind @ g for g in self.inverse_grip])
        self.grip_origin = np.stack([np.asarray(p.grip, np.float64)[:, 3] for p in character.props.values()])  # (W, 4)
        self.gpu_cull = gpu_cull
        self.lod_count = max(len(p.lods) for p in character.props.values())
        draws = len(self.names) * self.lod_count  # draw w * lod_count + lod: weapon w at that LOD
        if gpu_cull:
            if len(self.names) > 16:
                raise WeaponError(f"{len(self.names)} weapon meshes, more than the 16 the GPU cull lists")
            self._cull = self._objects.add(ctx.compute_shader(load_shader("weapon_cull.comp.glsl")))
            self._placed = self._objects.add(ctx.buffer(reserve=INSTANCE_DTYPE.itemsize))
            self._owner = self._objects.add(ctx.buffer(reserve=8))
            self._shown = self._objects.add(ctx.buffer(reserve=INSTANCE_DTYPE.itemsize))  # every mesh's list, one buffer
            self._commands = self._objects.add(ctx.buffer(reserve=draws * COMMAND_DTYPE.itemsize))
            self._ring = CountRing(ctx, self._objects, draws)
            self._shadow_shown = self._shadow_commands = None
            if shadows:
                self._shadow_shown = self._objects.add(ctx.buffer(reserve=INSTANCE_DTYPE.itemsize))
                self._shadow_commands = self._objects.add(ctx.buffer(reserve=CASCADES * draws * COMMAND_DTYPE.itemsize))
        self.shadows = shadows
        for prop in character.props.values():
            lods = prop.lods + (prop.lods[-1],) * (self.lod_count - len(prop.lods))
            for lod, mesh in enumerate(lods):
                vbo = self._objects.add(ctx.buffer(pack_rigid(mesh).tobytes()))
                ibo = self._objects.add(ctx.buffer(best_triangle_order(mesh.indices, len(mesh.positions)).tobytes()))
                inst = self._shown if gpu_cull else self._objects.add(ctx.buffer(reserve=INSTANCE_DTYPE.itemsize))
                shadow = []  # per cascade: the CPU path's lists (the GPU path's are one buffer, by baseInstance)
                if shadows:
                    shadow = [self._shadow_shown if gpu_cull else self._objects.add(ctx.buffer(reserve=INSTANCE_DTYPE.itemsize))
                              for _ in range(CASCADES)]
                self._meshes.append({"vbo": vbo, "ibo": ibo, "instances": inst, "shadow_instances": shadow, "count": 0,
                                     "shadow_counts": [0] * CASCADES, "vaos": {}, "triangles": mesh.triangle_count, "lod": lod})
        defines = {"SHADOWS": 1, "CASCADES": CASCADES} if shadows else {}
        self._programs = {
            "color": self._objects.add(ctx.program(vertex_shader=load_shader("weapon.vert.glsl"), fragment_shader=load_shader("skin.frag.glsl", defines))),
            "depth": self._objects.add(ctx.program(vertex_shader=load_shader("weapon.vert.glsl", {"DEPTH_ONLY": 1}), fragment_shader=load_shader("depth.frag.glsl"))),
        }
        if "u_shadow_map" in self._programs["color"]:
            self._programs["color"]["u_shadow_map"] = 3
        self.drawn = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3, 4), np.float32))
        self.last = {"weapons": 0, "drawn": 0, "draws": 0, "triangles": 0}

    def _vao(self, mesh: dict, kind: str, cascade: int = 0) -> moderngl.VertexArray:
        if (kind, cascade) not in mesh["vaos"]:
            prog = self._programs[kind]
            vertex = ("3f 2u", "in_position", "in_packed") if kind == "color" else ("3f 8x", "in_position")
            instances = mesh["shadow_instances"][cascade] if kind == "depth" else mesh["instances"]
            mesh["vaos"][kind, cascade] = self._objects.add(self.ctx.vertex_array(
                prog, [(mesh["vbo"], *vertex), (instances, "4f 4f 4f/i", "i_row0", "i_row1", "i_row2")], index_buffer=mesh["ibo"], index_element_size=4))
        return mesh["vaos"][kind, cascade]

    def matrices(self, read, frames: AgentFrames, weapon_of_agent: np.ndarray):
        """(agents, weapon indices, (K, 3, 4) float32 camera-relative weapon model rows, as uploaded)
        for the entries of `read` whose agent exists and is armed now, sorted by weapon.

        Float64 and vectorised, in planes (one (K, 4) array per matrix row, so every operation runs over
        contiguous memory): per weapon mesh one (K, 4) @ (4, 4) product per row for socket x bind x
        inverse grip, then the agent's heading, scale and position element-wise. numpy's batched 4x4
        matmul took 7 ms for 10,000 weapons on the dev container; this takes about 1.5 ms."""
        agents, rows = read.agents, read.rows
        keep = (agents < len(weapon_of_agent)) & (read.joints == self.socket_joint)
        agents, rows = agents[keep], rows[keep]
        weapon = weapon_of_agent[agents].astype(np.int16)
        armed = (weapon >= 0) & (weapon < len(self.names))
        agents, rows, weapon = agents[armed], rows[armed], weapon[armed]
        if not np.all(np.isfinite(rows)):
            raise WeaponError("a read-back socket matrix holds NaN or Inf")
        order = np.argsort(weapon, kind="stable")  # 16-bit keys: a radix sort
        agents, weapon = agents[order], weapon[order].astype(np.int64)
        socket = np.ascontiguousarray(rows[order].transpose(1, 0, 2), dtype=np.float64)  # (3, K, 4)
        starts = np.searchsorted(weapon, np.arange(len(self.names) + 1))
        local = np.empty(socket.shape)  # the weapon in the agent's model space
        for w in range(len(self.names)):
            a, b = starts[w], starts[w + 1]
            local[:, a:b] = socket[:, a:b] @ self._socket_to_weapon[w]
        position, scale, cs = frames.of(agents)
        k = scale[:, None]
        kc, ks = k * cs[:, 0:1], k * cs[:, 1:2]
        out = np.empty(local.shape)
        np.multiply(kc, local[0], out=out[0])
        out[0] += ks * local[2]
        np.multiply(k, local[1], out=out[1])
        np.multiply(kc, local[2], out=out[2])
        out[2] -= ks * local[0]
        out[:, :, 3] += position.T
        return agents, weapon, out.transpose(1, 0, 2).astype(np.float32)

    def attach(self, read, frames: AgentFrames, weapon_of_agent: np.ndarray, visible: np.ndarray | None = None,
               visibility=None, casting: np.ndarray | None = None, lod: np.ndarray | None = None) -> int:
        """Place and upload this frame's weapons (none when `read` is None). Returns how many.
        `visible`, `casting` and `lod`: the CPU cull's agents drawn, agents in each shadow cascade's
        volume ((cascades, N): their weapons' shadows are drawn there) and each agent's colour LOD
        (None: LOD0); `visibility`: on the GPU path, the body cull's per-agent visibility and LODs,
        which a compute pass filters the weapons by for both passes."""
        if read is None:
            agents, weapon, rows = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3, 4), np.float32)
        else:
            agents, weapon, rows = self.matrices(read, frames, np.asarray(weapon_of_agent))
        if self.gpu_cull:
            return self._attach_on_gpu(agents, weapon, rows, np.searchsorted(weapon, np.arange(len(self.names) + 1)), visibility)
        agent_lod = np.zeros(len(agents), np.int64) if lod is None else np.asarray(lod, np.int64)[agents]
        if self.shadows:
            for k in range(CASCADES):
                lit = np.ones(len(agents), bool) if casting is None else casting[k][agents]
                self._upload_cpu(weapon[lit], agent_lod[lit] + 1, rows[lit], "shadow_instances", "shadow_counts", k)
        if visible is not None:
            shown = visible[agents]
            agents, weapon, rows, agent_lod = agents[shown], weapon[shown], rows[shown], agent_lod[shown]
        self._upload_cpu(weapon, agent_lod, rows, "instances", "count")
        self.drawn = (agents, weapon, rows)
        self.last = {"weapons": int(len(agents)), "drawn": int(len(agents)), "draws": sum(1 for m in self._meshes if m["count"]),
                     "triangles": sum(m["count"] * m["triangles"] for m in self._meshes)}
        return len(agents)

    def _upload_cpu(self, weapon: np.ndarray, lod: np.ndarray, rows: np.ndarray, buffer: str, count: str, cascade: int | None = None) -> None:
        """The CPU path: each (weapon, LOD) mesh's rows into its `buffer`, their number in `count`
        (the shadow lists' of one `cascade`)."""
        key = weapon * self.lod_count + np.minimum(lod, self.lod_count - 1)
        order = np.argsort(key, kind="stable")
        rows = rows[order]
        starts = np.searchsorted(key[order], np.arange(len(self._meshes) + 1))
        for d, mesh in enumerate(self._meshes):
            chosen = rows[starts[d]:starts[d + 1]]
            target = mesh[buffer] if cascade is None else mesh[buffer][cascade]
            if cascade is None:
                mesh[count] = len(chosen)
            else:
                mesh[count][cascade] = len(chosen)
            size = max(chosen.nbytes, INSTANCE_DTYPE.itemsize)
            if target.size != size:
                target.orphan(size)
            if len(chosen):
                target.write(chosen.tobytes())

    def _attach_on_gpu(self, agents, weapon, rows, starts, visibility) -> int:
        """Every placed weapon uploaded once; the weapon cull writes each into its (weapon, LOD) range:
        LOD l's lists follow one another, each `k` long, weapon w's part of each starting at starts[w];
        the shadow lists hold one such set per cascade, one after the other."""
        if visibility is None:
            raise WeaponError("the GPU weapon cull needs the body cull's visibility buffer")
        k = len(agents)
        sets = 1 + (CASCADES if self._shadow_shown is not None else 0)  # the colour lists, then each cascade's
        for buf, size in ((self._placed, rows.nbytes), (self._shown, rows.nbytes * self.lod_count),
                          (self._shadow_shown, rows.nbytes * self.lod_count * (sets - 1))):
            if buf is not None and buf.size != max(size, INSTANCE_DTYPE.itemsize):
                buf.orphan(max(size, INSTANCE_DTYPE.itemsize))
        commands = np.zeros(len(self._meshes), COMMAND_DTYPE)
        commands["count"] = [m["triangles"] * 3 for m in self._meshes]
        lod = np.arange(len(self._meshes)) % self.lod_count
        commands["base_instance"] = lod * k + np.repeat(starts[:-1], self.lod_count)
        self._commands.write(commands.tobytes())
        if sets > 1:
            shadow = np.tile(commands, CASCADES)
            shadow["base_instance"] += np.repeat(np.arange(CASCADES, dtype=np.uint32) * np.uint32(self.lod_count * k), len(self._meshes))
            self._shadow_commands.write(shadow.tobytes())
        for d, mesh in enumerate(self._meshes):  # placed: the GPU draws the visible of them
            w = d // self.lod_count
            mesh["count"] = int(starts[w + 1] - starts[w])
            mesh["shadow_counts"] = [mesh["count"]] * CASCADES
        if k:
            self._placed.write(np.ascontiguousarray(rows))
            owner = np.stack([agents, weapon], axis=1).astype(np.uint32)
            if self._owner.size != owner.nbytes:
                self._owner.orphan(owner.nbytes)
            self._owner.write(owner.tobytes())
            self._cull["u_count"] = k
            self._cull["u_lod_count"] = self.lod_count
            first = np.zeros(16, np.uint32)
            first[: len(self.names)] = starts[:-1]
            self._cull["u_start"].write(first.tobytes())
            for run in range(sets):  # the colour pass's weapons, then each shadow cascade's
                shown, command_buffer = (self._shown, self._commands) if run == 0 else (self._shadow_shown, self._shadow_commands)
                self._cull["u_shadow"] = run  # 0: colour; 1 + k: cascade k
                self._cull["u_list_base"] = max(run - 1, 0) * self.lod_count * k
                self._cull["u_command_base"] = max(run - 1, 0) * len(self._meshes)
                for binding, buf in enumerate((self._placed, self._owner, shown, command_buffer, visibility)):
                    buf.bind_to_storage_buffer(binding)
                self._cull.run(group_x=(k + GROUP_SIZE - 1) // GROUP_SIZE)
            self.ctx.memory_barrier(VERTEX_ATTRIB_ARRAY | COMMAND | BUFFER_UPDATE)
            self._ring.queue(self._commands)
        else:
            self._ring.zero()
        self.drawn = (agents, weapon, rows)
        self.last = {"weapons": int(k)}
        self.refresh_counts()
        return k

    def refresh_counts(self, wait: bool = False) -> None:
        """On the GPU path: what was drawn, from the newest counts handed back (`wait`: every queued frame's)."""
        if not self.gpu_cull:
            return
        counts = self._ring.read(wait).astype(np.int64)
        self.last.update(drawn=int(counts.sum()), draws=int(np.count_nonzero(counts)),
                         triangles=int(sum(int(c) * m["triangles"] for c, m in zip(counts, self._meshes))))

    def casts_shadows(self) -> bool:
        """Whether the shadow pass has weapons to draw (the agents in the sun's volume may be out of view)."""
        return any(any(m["shadow_counts"]) for m in self._meshes)

    def _render(self, d: int, mesh: dict, kind: str, cascade: int = 0) -> None:
        count = mesh["shadow_counts"][cascade] if kind == "depth" else mesh["count"]
        if not count:
            return
        if self.gpu_cull:
            commands = self._shadow_commands if kind == "depth" else self._commands
            first = d + (cascade * len(self._meshes) if kind == "depth" else 0)
            self._vao(mesh, kind).render_indirect(commands, moderngl.TRIANGLES, count=1, first=first)
        else:
            self._vao(mesh, kind, cascade if kind == "depth" else 0).render(moderngl.TRIANGLES, instances=count)

    def grip_points(self) -> np.ndarray:
        """(K, 3) float64: the grip point of each drawn weapon, through the float32 rows the GPU got."""
        agents, weapon, rows = self.drawn
        return np.einsum("kij,kj->ki", rows.astype(np.float64), self.grip_origin[weapon])

    def depth_pass(self, view, renderer) -> None:
        """Into each shadow cascade's tile (``renderer.shadow_tiles``), after the crowd's shadow pass."""
        prog = self._programs["depth"]
        for k, matrix in renderer.shadow_tiles(view):
            prog["u_view_proj"].write(gl_bytes(matrix))
            for d, mesh in enumerate(self._meshes):
                self._render(d, mesh, "depth", k)

    def color_pass(self, framebuffer, view, renderer) -> None:
        """`view`: this frame's ``FrameView``; `renderer` lights the weapons as it lights the crowd."""
        framebuffer.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        prog = self._programs["color"]
        prog["u_view_proj"].write(gl_bytes(view.view_proj))
        renderer.set_lighting(prog, view)
        for d, mesh in enumerate(self._meshes):
            self._render(d, mesh, "color")

    def gpu_bytes(self) -> int:
        return self._objects.gpu_bytes()

    def release(self) -> None:
        if getattr(self, "_ring", None) is not None:
            self._ring.drop()
        self._objects.release()
        self._meshes = []
