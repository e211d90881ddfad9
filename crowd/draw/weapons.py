"""Attach stage: weapons placed on the CPU from read-back socket matrices, drawn one instanced draw per
(weapon, LOD) mesh (on the GPU path, one multi-draw over buffers all the meshes share). A weapon is drawn at its agent's LOD (the prop's coarsest where it has fewer), and
its shadow one LOD coarser, as the body's is.

Contract: ``attach(read, agents_frame, weapon_of_agent)``:
- ``read`` (readback.SocketRead): socket skinning-matrix rows of some frame's armed agents;
- ``agents_frame`` (AgentFrames): each agent's transform exactly as the crowd's vertex shader applies
  it this frame: camera-relative position, uniform scale, and the heading's cos and sin as the snorm16
  values the instance record carries, so weapon and hand go through the same numbers;
- ``weapon_of_agent``: (N,) weapon index per agent (-1: unarmed).

Per entry: the weapon in its agent's model space = socket skinning matrix x socket bind x
inverse(grip), in float32, vectorised (``placements``). The agent's own transform is applied on the
GPU, by weapon.vert.glsl with the arithmetic of skin.vert.glsl, from the agent's part of the instance
(the CPU path writes it from ``agents_frame``; the GPU path's weapon cull copies it from the body's
record): weapon and hand go through the same numbers and the same expressions. An entry whose agent
is unarmed now, or out of range, is dropped without touching the others. ``drawn`` keeps what was
uploaded (agents, weapon indices, model-space rows) so that the error of the frame as drawn can be measured.

Culling: on the CPU cull path ``attach`` is given the visible set and uploads only those weapons. On the
GPU path (``gpu_cull``) the CPU does not know it: every armed agent's weapon is uploaded with its
owner, and a compute pass (shaders/weapon_cull.comp.glsl) keeps those whose agent the body cull marked
visible, compacted per (weapon, LOD) mesh and counted in indirect commands, so a weapon is drawn exactly
when its agent is, at its agent's LOD. On the transform-feedback path (``feedback_cull``, GL 4.0 to 4.2)
the same: every placed weapon is uploaded with its agent's transform (as on the CPU path) and its agent's
number, and feedback draws (shaders/weapon_feedback.*.glsl, 4 (weapon, LOD, pass) lists each, a vertex stream
a list) keep those whose agent the body cull's visibility texture shows there, into each mesh's list of each
pass, drawn with glDrawElementsIndirect (crowd.draw.feedback_cull). With shadows on, each shadow cascade's tile gets the weapons of
the agents in that cascade's volume (the body cull's shadow lists), from lists of their own on both paths. ``last["weapons"]`` counts the weapons placed, ``last["drawn"]`` those drawn (on the GPU
path as the GPU hands the counts back, a frame or two late; ``refresh_counts(wait=True)`` at a run's end).

Dropped weapons: given ``fallen`` (agents dying or dead), a weapon that was in hand last frame and is
not now drops (``on_ground``) and is drawn lying there, in its agent's model space, until the agent
is up again; ``last["dropped"]`` counts them. They are not in ``drawn`` (which the in-hand error measures).
"""

from __future__ import annotations

import moderngl
import numpy as np

from ..errors import CrowdError
from ..gl import GLObjects, GLStage, load_shader, set_uniforms
from .drawn_counts import CountsWhenAsked
from .feedback_cull import STREAMS, FeedbackCounter, TransformFeedbacks, capture, stream_groups, stream_varyings
from .gpu_cull import BUFFER_UPDATE, COMMAND, COMMAND_DTYPE, GROUP_SIZE, VERTEX_ATTRIB_ARRAY, CountRing
from ..asset.model import Character, RigidMesh, cast_weapons
from ..asset.vertex_cache import best_triangle_order
from .packing import UNLIT_BIT, heading_snorm16, pack_colors, pack_normals, shared_buffers, write_heading
from .draw_programs import fixed_units, lighting_defines
from .frame_block import FRAME_DEFINES
from .view import gl_bytes
from .shadows import CASCADES

VERTEX_DTYPE = np.dtype([("position", "<f4", 3), ("packed", "<u4", 2)])
# A weapon instance: its 3x4 model matrix in its agent's model space, and the agent's transform as the
# body's instance record carries it (camera-relative position and scale; fields.z the heading), which
# weapon.vert.glsl applies as skin.vert.glsl does. 80 bytes, std430's layout of the same struct.
INSTANCE_DTYPE = np.dtype([("rows", "<f4", (3, 4)), ("position_scale", "<f4", 4), ("fields", "<u4", 4)])


class WeaponError(CrowdError, ValueError):
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

    def of(self, agents: np.ndarray, dtype=np.float64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(position float32 (M, 3), scale (M,), cos_sin (M, 2)) of those agents, the last two in `dtype`."""
        rel = (self._position[agents] - self._eye[None]).astype(np.float32)
        cs = heading_snorm16(self._yaw[agents])
        return rel, self._scale[agents].astype(dtype), cs.astype(dtype) / dtype(32767.0)  # as unpackSnorm2x16 divides

    def instances(self, agents: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(K,) INSTANCE_DTYPE: model-space weapon rows (K, 3, 4) with their agents' transforms, as the
        body's instance records carry them (the CPU path's weapon instances)."""
        out = np.zeros(len(agents), INSTANCE_DTYPE)
        out["rows"] = rows
        out["position_scale"][:, :3] = self._position[agents] - self._eye[None]
        out["position_scale"][:, 3] = self._scale[agents]
        write_heading(self._yaw[agents], out["fields"][:, 2])
        return out

    def points(self, agents: np.ndarray, model_points: np.ndarray) -> np.ndarray:
        """(M, 3) float64: model-space points of those agents placed as the shader places them:
        x' = position + scale * heading(x), the heading turning +Z toward (sin, cos)."""
        rel, k, cs = self.of(agents)
        p = np.asarray(model_points, np.float64)
        c, s = cs[:, 0], cs[:, 1]
        return rel + k[:, None] * np.stack([c * p[:, 0] + s * p[:, 2], p[:, 1], c * p[:, 2] - s * p[:, 0]], axis=1)


def pack_rigid(mesh: RigidMesh, to_socket: np.ndarray) -> np.ndarray:
    """The mesh's vertices moved into its socket's space by the affine `to_socket` (4, 4) in float64
    (socket bind x inverse grip, fixed per weapon): the read-back socket skinning matrix then places
    them as it is, and the CPU does no arithmetic per weapon."""
    v = np.zeros(len(mesh.positions), VERTEX_DTYPE)
    linear = to_socket[:3, :3]
    v["position"] = np.asarray(mesh.positions, np.float64) @ linear.T + to_socket[:3, 3]
    normals = np.asarray(mesh.normals, np.float64) @ np.linalg.inv(linear)  # the inverse transpose, for any scale
    v["packed"][:, 0] = pack_normals(normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)) | \
        (np.uint32(UNLIT_BIT) if mesh.unlit else np.uint32(0))
    v["packed"][:, 1] = pack_colors(mesh.colors, mesh.base_color, len(v))
    return v


class WeaponRenderer(CountsWhenAsked, GLStage):
    """Owns the weapon meshes, their instance buffers and programs. ``last``: the last frame's weapons placed
    in hand, dropped, drawn, draws and triangles (on the GPU paths the last three as the GPU hands them back)."""

    def __init__(self, ctx: moderngl.Context, characters, shadows: bool, gpu_cull: bool = False, feedback_cull: bool = False):
        """`characters`: one Character, or the cast's; every prop of every character that has a socket is
        a weapon, numbered across the cast in its order (``first_weapon`` says where each one's start).
        `gpu_cull` (GL 4.3) or `feedback_cull` (GL 4.0): culled on the GPU by the body cull's visibility."""
        self._objects = GLObjects()
        self._meshes = []
        cast = [characters] if isinstance(characters, Character) else list(characters)
        if not any(c.armed for c in cast):
            names = ", ".join(repr(c.name) for c in cast)
            raise WeaponError(f"character {names} has no weapons to hold (props and a socket joint are both needed)")
        self.ctx = ctx
        # Per character of the cast: its first weapon's number (its props come in order); every weapon's name.
        self.first_weapon, self.names = cast_weapons(cast)
        props, joints, binds = [], [], []
        for c in cast:
            if not c.armed:
                continue
            joint = int(next(iter(c.sockets.values())))
            bind = np.linalg.inv(np.asarray(c.skeleton.inverse_bind, np.float64))[joint]  # the socket joint's model matrix at bind
            for prop in c.props.values():
                props.append(prop)
                joints.append(joint)
                binds.append(bind)
        self.socket_joints = np.array(joints, np.int64)  # per weapon: the socket joint of its character
        self.socket_bind = np.stack(binds)  # per weapon (W, 4, 4): that socket's model matrix at bind
        self.inverse_grip = np.stack([np.linalg.inv(np.asarray(p.grip, np.float64)) for p in props])
        # Per weapon mesh: the socket's skinning matrix times this gives the weapon in model space. It is
        # baked into the mesh's vertices (pack_rigid), so an instance is the read-back socket rows as they are.
        self._socket_to_weapon = np.einsum("wij,wjk->wik", self.socket_bind, self.inverse_grip)
        grip_origin = np.stack([np.asarray(p.grip, np.float64)[:, 3] for p in props])  # (W, 4)
        self._grip_point = grip_origin[:, :3]  # (W, 3): the grip point in each weapon's space
        self._grip_in_socket = np.einsum("wij,wj->wi", self._socket_to_weapon, grip_origin)  # the grip point, as baked
        self.gpu_cull = gpu_cull
        self.feedback_cull = feedback_cull and not gpu_cull
        self.lod_count = max(len(p.lods) for p in props)
        draws = len(self.names) * self.lod_count  # draw w * lod_count + lod: weapon w at that LOD
        if gpu_cull:
            self._cull = self._objects.add(ctx.compute_shader(load_shader("weapon_cull.comp.glsl", {"WEAPONS": len(self.names)})))
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
        shared = []  # the GPU path's (vertices, indices) of every mesh, for one vertex and one index buffer
        for w, prop in enumerate(props):
            lods = prop.lods + (prop.lods[-1],) * (self.lod_count - len(prop.lods))
            for lod, mesh in enumerate(lods):
                vertices, indices = pack_rigid(mesh, self._socket_to_weapon[w]), best_triangle_order(mesh.indices, len(mesh.positions))
                if gpu_cull:
                    shared.append((vertices, indices))
                    vbo = ibo = None
                else:
                    vbo = self._objects.add(ctx.buffer(vertices.tobytes()))
                    ibo = self._objects.add(ctx.buffer(indices.tobytes()))
                # (the feedback path's lists: one buffer per mesh and pass, as the CPU path's, written by the GPU)
                inst = self._shown if gpu_cull else self._objects.add(ctx.buffer(reserve=INSTANCE_DTYPE.itemsize))
                shadow = []  # per cascade: the CPU path's lists (the GPU path's are one buffer, by baseInstance)
                if shadows:
                    shadow = [self._shadow_shown if gpu_cull else self._objects.add(ctx.buffer(reserve=INSTANCE_DTYPE.itemsize))
                              for _ in range(CASCADES)]
                self._meshes.append({"vbo": vbo, "ibo": ibo, "instances": inst, "shadow_instances": shadow, "count": 0,
                                     "shadow_counts": [0] * CASCADES, "vaos": {}, "triangles": mesh.triangle_count, "lod": lod,
                                     "first_index": 0, "base_vertex": 0})
        # On the GPU path a pass draws every (weapon, LOD) mesh with one multi-draw over the shared
        # buffers (24 calls a frame before, with shadows), each command starting at its mesh's indices.
        self._merged = None
        if gpu_cull:
            vbo, ibo, starts = shared_buffers(ctx, shared)
            self._merged = {"vbo": self._objects.add(vbo), "ibo": self._objects.add(ibo),
                            "instances": self._shown, "shadow_instances": [self._shadow_shown] * CASCADES, "vaos": {}}
            for mesh, (first, base) in zip(self._meshes, starts):
                mesh["first_index"], mesh["base_vertex"] = first, base
        if self.feedback_cull:
            self._feedback = self._objects.add(ctx.program(vertex_shader=load_shader("weapon_feedback.vert.glsl"),
                                                           geometry_shader=load_shader("weapon_feedback.geom.glsl"),
                                                           varyings=stream_varyings(["row0", "row1", "row2", "position_scale", "fields"])))
            self._feedback["u_visible"] = 0
            self._feedback["u_lod_count"] = self.lod_count
            self._placed = self._objects.add(ctx.buffer(reserve=INSTANCE_DTYPE.itemsize))
            self._spare = self._objects.add(ctx.buffer(reserve=INSTANCE_DTYPE.itemsize))  # a group's unused streams
            self._placed_vao = self._objects.add(ctx.vertex_array(self._feedback, [(self._placed, "4f 4f 4f 4f 4u", "i_row0", "i_row1", "i_row2",
                                                                                     "i_position_scale", "i_fields")]))
            passes = 1 + (CASCADES if shadows else 0)
            self._slots = [(d, run) for run in range(passes) for d in range(len(self._meshes))]  # list k: mesh d of pass run
            self._groups = stream_groups(self._slots, lambda slot: 0)
            self._feedbacks = self._objects.add(TransformFeedbacks(len(self._groups)))
            self._counter = FeedbackCounter(ctx, self._objects, [(self._meshes[d]["triangles"] * 3, k) for k, (d, _) in enumerate(self._slots)],
                                            len(self._slots))
            self._capacity = np.zeros(len(self.names), np.int64)  # weapons each mesh's lists hold
        defines = lighting_defines(shadows)
        unlit = {"UNLIT_PIECES": 1} if any(m.unlit for p in props for m in p.lods) else {}  # KHR_materials_unlit props
        self._programs = {
            "color": self._objects.add(ctx.program(vertex_shader=load_shader("weapon.vert.glsl", {**FRAME_DEFINES, **unlit}),
                                                   fragment_shader=load_shader("skin.frag.glsl", {**defines, **unlit}))),
            "depth": self._objects.add(ctx.program(vertex_shader=load_shader("weapon.vert.glsl", {"DEPTH_ONLY": 1}), fragment_shader=load_shader("depth.frag.glsl"))),
        }
        fixed_units(self._programs["color"])
        self.drawn = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3, 4), np.float32))
        # Weapons lying on the ground (agents, weapon, rows in the fallen agent's model space) until their
        # agent gets up again; and what was in hand last frame, where the next drop comes from.
        self.dropped = self._held_before = self.drawn
        # How far below its grip point each weapon reaches along its +Z, the axis a dropped weapon lies on.
        self._low_z = np.array([float(np.min(np.asarray(prop.lods[0].positions, np.float64)[:, 2])) for prop in props]) - self._grip_point[:, 2]
        self._last = {"weapons": 0, "dropped": 0, "drawn": 0, "draws": 0, "triangles": 0}
        self._counts_due = False  # the GPU paths' counts are read when ``last`` is, not every frame
        self._command_template = None

    def _vao(self, mesh: dict, kind: str, cascade: int = 0) -> moderngl.VertexArray:
        if (kind, cascade) not in mesh["vaos"]:
            prog = self._programs[kind]
            vertex = ("3f 2u", "in_position", "in_packed") if kind == "color" else ("3f 8x", "in_position")
            instances = mesh["shadow_instances"][cascade] if kind == "depth" else mesh["instances"]
            mesh["vaos"][kind, cascade] = self._objects.add(self.ctx.vertex_array(
                prog, [(mesh["vbo"], *vertex), (instances, "4f 4f 4f 4f 8x 1u 4x/i", "i_row0", "i_row1", "i_row2", "i_position_scale", "i_heading")], index_buffer=mesh["ibo"], index_element_size=4))
        return mesh["vaos"][kind, cascade]

    def placements(self, read, weapon_of_agent: np.ndarray):
        """(agents, weapon indices, (K, 3, 4) float32 socket skinning-matrix rows) for the entries of
        `read` whose agent exists and is armed now, in the read's order.

        No arithmetic: the weapon meshes' vertices are in their socket's space (pack_rigid), and the
        agent's transform is applied by weapon.vert.glsl, so the read-back rows are the instances'
        model rows as they are. Only a frame with entries to drop (an agent gone, unarmed, or dead
        since its socket was gathered) copies them. Composing socket x grip x agent in float64 numpy
        took 11 ms for 50,000 weapons on the dev container."""
        agents, rows = read.agents, read.rows
        present = agents < len(weapon_of_agent)
        if present.all():
            weapon = weapon_of_agent[agents].astype(np.int64)
        else:
            weapon = np.full(len(agents), -1, np.int64)
            weapon[present] = weapon_of_agent[agents[present]]
        keep = (weapon >= 0) & (weapon < len(self.names))
        keep[keep] = read.joints[keep] == self.socket_joints[weapon[keep]]  # the socket of the weapon held now
        if not keep.all():
            entry = np.flatnonzero(keep)
            agents, weapon, rows = agents[entry], weapon[entry], rows[entry]
        rows = np.asarray(rows, np.float32)
        # All finite exactly when their float64 sum is (NaN and Inf propagate, Inf - Inf is NaN, and no
        # float32 values' sum overflows float64): one pass and no boolean temporary.
        if not np.isfinite(rows.sum(dtype=np.float64)):
            raise WeaponError("a read-back socket matrix holds NaN or Inf")
        return agents, weapon, rows

    def attach(self, read, frames: AgentFrames, weapon_of_agent: np.ndarray, visible: np.ndarray | None = None,
               visibility=None, casting: np.ndarray | None = None, lod: np.ndarray | None = None, fallen: np.ndarray | None = None) -> int:
        """Place and upload this frame's weapons (none when `read` is None). Returns how many.
        `visible`, `casting` and `lod`: the CPU cull's agents drawn, agents in each shadow cascade's
        volume ((cascades, N): their weapons' shadows are drawn there) and each agent's colour LOD
        (None: LOD0); `visibility`: on the GPU path, the body cull's buffers of per-agent visibility and
        LODs, which a compute pass filters the weapons by for both passes, and of agent records, whose
        transform it applies to each weapon placed in its agent's model space. `fallen` (N,): agents down
        (dying or dead), whose weapon leaves the hand for the ground (``dropped``) until they get up."""
        if read is None:
            agents, weapon, rows = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3, 4), np.float32)
        else:
            agents, weapon, rows = self.placements(read, np.asarray(weapon_of_agent))
        if fallen is not None:
            self._drop(agents, np.asarray(fallen, bool))
        self._held_before = (agents, weapon, rows)
        held = len(agents)  # the placed weapons come first, the dropped ones after them
        if len(self.dropped[0]):  # (a copy of every placed row: only when something lies on the ground)
            agents, weapon, rows = (np.concatenate([a, b]) for a, b in zip((agents, weapon, rows), self.dropped))
        if self.gpu_cull:
            return self._attach_on_gpu(agents, weapon, rows, np.concatenate([[0], np.cumsum(np.bincount(weapon, minlength=len(self.names)))]), visibility, held)
        if self.feedback_cull:
            return self._attach_on_feedback(agents, weapon, rows, frames, visibility, held)
        agent_lod = np.zeros(len(agents), np.int64) if lod is None else np.asarray(lod, np.int64)[agents]
        instances = frames.instances(agents, rows)
        if self.shadows:
            for k in range(CASCADES):
                lit = np.ones(len(agents), bool) if casting is None else casting[k][agents]
                self._upload_cpu(weapon[lit], agent_lod[lit] + 1, instances[lit], "shadow_instances", "shadow_counts", k)
        in_hand = np.arange(len(agents)) < held
        if visible is not None:
            shown = visible[agents]
            agents, weapon, rows, agent_lod, instances, in_hand = (a[shown] for a in (agents, weapon, rows, agent_lod, instances, in_hand))
        self._upload_cpu(weapon, agent_lod, instances, "instances", "count")
        self.drawn = (agents[in_hand], weapon[in_hand], rows[in_hand])
        self._last = {"weapons": int(np.count_nonzero(in_hand)), "dropped": len(self.dropped[0]), "drawn": int(len(agents)),
                     "draws": sum(1 for m in self._meshes if m["count"]), "triangles": sum(m["count"] * m["triangles"] for m in self._meshes)}
        return len(agents)

    def _drop(self, held: np.ndarray, fallen: np.ndarray) -> None:
        """Weapons whose agent fell this frame (in hand last frame, `fallen` now, not in hand now) drop to
        the ground; those of agents up again (respawned) or gone are removed."""
        agents, weapon, rows = self.dropped
        n = len(fallen)
        stay = (agents < n) & fallen[np.minimum(agents, max(n - 1, 0))] if n else np.zeros(len(agents), bool)
        before_agents, before_weapon, before_rows = self._held_before
        # Flags over the crowd, not np.isin (a sort: 2 ms for 50,000 weapons): in hand now, or down already.
        taken = np.zeros(n + 1, bool)
        taken[held[held < n]] = True
        taken[agents[stay]] = True
        new = (before_agents < n) & ~taken[np.minimum(before_agents, n)]
        new[new] = fallen[before_agents[new]]
        self.dropped = (np.concatenate([agents[stay], before_agents[new]]), np.concatenate([weapon[stay], before_weapon[new]]),
                        np.concatenate([rows[stay], self.on_ground(before_rows[new], before_weapon[new])]))

    def on_ground(self, socket_rows: np.ndarray, weapon: np.ndarray) -> np.ndarray:
        """(K, 3, 4) float32 instance rows (socket-space convention, in the agent's model space) of
        weapons dropped from hands whose socket rows were `socket_rows`: each lies flat on the ground
        (the agent's y = 0) with its handle (+Y) along the direction it pointed, projected onto the
        ground, its +Z up, and its grip point straight below where the hand held it. In float64."""
        k = len(weapon)
        if not k:
            return np.zeros((0, 3, 4), np.float32)
        m = self._socket_to_weapon[weapon]  # (K, 4, 4): weapon space -> socket space
        held = np.einsum("kij,kjl->kil", np.asarray(socket_rows, np.float64), m)  # (K, 3, 4): the weapon in model space
        along = held[:, [0, 2], 1]  # the handle's direction on the ground (x, z)
        length = np.linalg.norm(along, axis=1)
        sideways = held[:, [0, 2], 0]  # a handle pointing straight down lies along the weapon's +X instead
        along = np.where((length > 1e-6)[:, None], along, sideways) / np.maximum(np.where(length > 1e-6, length, np.linalg.norm(sideways, axis=1)), 1e-12)[:, None]
        dx, dz = along[:, 0], along[:, 1]
        ground = np.zeros((k, 4, 4))
        ground[:, :3, 0] = np.stack([-dz, np.zeros(k), dx], axis=1)  # +X: Y x Z, right-handed
        ground[:, :3, 1] = np.stack([dx, np.zeros(k), dz], axis=1)
        ground[:, 1, 2] = 1.0
        ground[:, 3, 3] = 1.0
        g = self._grip_point[weapon]
        hand = np.einsum("kij,kj->ki", held[:, :, :3], g) + held[:, :, 3]  # the grip point in hand
        below = np.stack([hand[:, 0], -self._low_z[weapon], hand[:, 2]], axis=1)
        ground[:, :3, 3] = below - np.einsum("kij,kj->ki", ground[:, :3, :3], g)
        return (ground @ np.linalg.inv(m))[:, :3].astype(np.float32)  # rows x (M x p) = ground x p

    def _upload_cpu(self, weapon: np.ndarray, lod: np.ndarray, instances: np.ndarray, buffer: str, count: str, cascade: int | None = None) -> None:
        """The CPU path: each (weapon, LOD) mesh's instances (INSTANCE_DTYPE) into its `buffer`, their
        number in `count` (the shadow lists' of one `cascade`)."""
        key = weapon * self.lod_count + np.minimum(lod, self.lod_count - 1)
        order = np.argsort(key, kind="stable")
        rows = instances[order]
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

    def _attach_on_gpu(self, agents, weapon, rows, starts, visibility, held: int) -> int:
        """Every placed weapon uploaded once; the weapon cull writes each into its (weapon, LOD) range:
        LOD l's lists follow one another, each `k` long, weapon w's part of each starting at starts[w];
        the shadow lists hold one such set per cascade, one after the other."""
        if visibility is None:
            raise WeaponError("the GPU weapon cull needs the body cull's visibility and record buffers")
        visible, records = visibility
        k = len(agents)
        sets = 1 + (CASCADES if self._shadow_shown is not None else 0)  # the colour lists, then each cascade's
        shown = k * INSTANCE_DTYPE.itemsize  # a weapon's instance, as the weapon cull writes it
        for buf, size in ((self._placed, rows.nbytes), (self._shown, shown * self.lod_count),
                          (self._shadow_shown, shown * self.lod_count * (sets - 1))):
            if buf is not None and buf.size != max(size, INSTANCE_DTYPE.itemsize):
                buf.orphan(max(size, INSTANCE_DTYPE.itemsize))
        if self._command_template is None:  # (what does not change from frame to frame, made once)
            template = np.zeros(len(self._meshes), COMMAND_DTYPE)
            template["count"] = [m["triangles"] * 3 for m in self._meshes]
            template["first_index"] = [m["first_index"] for m in self._meshes]
            template["base_vertex"] = [m["base_vertex"] for m in self._meshes]
            self._command_template = template
        commands = self._command_template.copy()
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
            owner = np.empty((k, 2), np.uint32)
            owner[:, 0], owner[:, 1] = agents, weapon
            if self._owner.size != owner.nbytes:
                self._owner.orphan(owner.nbytes)
            self._owner.write(owner)
            self._cull["u_count"] = k
            self._cull["u_lod_count"] = self.lod_count
            self._cull["u_start"].write(np.asarray(starts[:-1], np.uint32).tobytes())
            for run in range(sets):  # the colour pass's weapons, then each shadow cascade's
                shown, command_buffer = (self._shown, self._commands) if run == 0 else (self._shadow_shown, self._shadow_commands)
                self._cull["u_shadow"] = run  # 0: colour; 1 + k: cascade k
                self._cull["u_list_base"] = max(run - 1, 0) * self.lod_count * k
                self._cull["u_command_base"] = max(run - 1, 0) * len(self._meshes)
                for binding, buf in enumerate((self._placed, self._owner, shown, command_buffer, visible, records)):
                    buf.bind_to_storage_buffer(binding)
                self._cull.run(group_x=(k + GROUP_SIZE - 1) // GROUP_SIZE)
            self.ctx.memory_barrier(VERTEX_ATTRIB_ARRAY | COMMAND | BUFFER_UPDATE)
            self._ring.queue(self._commands)
        else:
            self._ring.zero()
        self.drawn = (agents[:held], weapon[:held], rows[:held])
        self._last.update(weapons=held, dropped=k - held)
        self._counts_due = True
        return k

    def _attach_on_feedback(self, agents, weapon, rows, frames: AgentFrames, visible, held: int) -> int:
        """Every placed weapon uploaded once, with its agent's transform and number; a feedback draw per
        mesh and pass keeps those the body cull's visibility texture (`visible`) shows there."""
        if visible is None:
            raise WeaponError("the weapons' feedback cull needs the body cull's visibility texture")
        k = len(agents)
        self.drawn = (agents[:held], weapon[:held], rows[:held])
        self._last.update(weapons=held, dropped=k - held)
        if not k:  # nothing to draw: the commands too, as the passes draw from them without knowing
            self._counter.zero()
            for mesh in self._meshes:
                mesh["count"], mesh["shadow_counts"] = 0, [0] * CASCADES
            self._counts_due = True
            return 0
        instances = frames.instances(agents, rows)
        instances["fields"][:, 0] = agents
        instances["fields"][:, 1] = weapon
        if self._placed.size != instances.nbytes:
            self._placed.orphan(instances.nbytes)
        self._placed.write(instances)
        # Each mesh's lists hold its weapon's placed count, grown by doubling and shrunk only at a quarter,
        # so a crowd whose armed count wanders does not re-allocate every frame.
        need = np.bincount(weapon, minlength=len(self.names))
        resize = (self._capacity < need) | (self._capacity > 4 * need + 256)
        for w in np.flatnonzero(resize):
            self._capacity[w] = 1 << int(max(need[w], 1) - 1).bit_length()
            for mesh in self._meshes[w * self.lod_count:(w + 1) * self.lod_count]:
                for buf in [mesh["instances"], *mesh["shadow_instances"]]:
                    buf.orphan(int(self._capacity[w]) * INSTANCE_DTYPE.itemsize)
        visible.use(0)
        p = self._feedback
        p["u_visible_width"] = visible.width
        lists = lambda d, run: self._meshes[d]["instances"] if run == 0 else self._meshes[d]["shadow_instances"][run - 1]  # noqa: E731
        self._counter.target.use()  # (a draw needs a complete framebuffer bound, even one that writes no pixels)
        self.ctx.enable(moderngl.RASTERIZER_DISCARD)  # (the feedback draws write lists, not pixels)
        try:
            for g, group in enumerate(self._groups):
                passes, weapons, lods = [-1] * STREAMS, [0] * STREAMS, [0] * STREAMS
                for s, index in enumerate(group):
                    d, passes[s] = self._slots[index]
                    weapons[s], lods[s] = d // self.lod_count, d % self.lod_count
                p["u_slot_pass"], p["u_slot_weapon"], p["u_slot_lod"] = passes, weapons, lods
                into = [lists(*self._slots[index]) for index in group] + [self._spare] * (STREAMS - len(group))
                capture(p, self._placed_vao, self._feedbacks[g], into, 0, k)
        finally:
            self.ctx.disable(moderngl.RASTERIZER_DISCARD)
        self._counter.begin()
        for g, group in enumerate(self._groups):
            for s, index in enumerate(group):
                self._counter.count_stream(self._feedbacks[g], s, index)
        self._counter.finish()
        for d, mesh in enumerate(self._meshes):  # placed: the GPU draws the visible of them
            mesh["count"] = int(need[d // self.lod_count])
            mesh["shadow_counts"] = [mesh["count"]] * CASCADES
        self._counts_due = True
        return k

    def placed_any(self) -> bool:
        """Whether the last frame placed a weapon, in hand or on the ground (its colour pass has work)."""
        return bool(self._last["weapons"] or self._last["dropped"])

    def refresh_counts(self, wait: bool = False) -> None:
        """On the GPU paths: what was drawn, from the newest counts handed back (`wait`: every queued frame's)."""
        if self.feedback_cull:
            counts = self._counter.counts(wait)[: len(self._meshes)].astype(np.int64)
        elif self.gpu_cull:
            counts = self._ring.read(wait).astype(np.int64)
        else:
            return
        self._counts_due = False
        self._last.update(drawn=int(counts.sum()), draws=int(np.count_nonzero(counts)),
                         triangles=int(sum(int(c) * m["triangles"] for c, m in zip(counts, self._meshes))))

    def casts_shadows(self) -> bool:
        """Whether the shadow pass has weapons to draw (the agents in the sun's volume may be out of view)."""
        return any(any(m["shadow_counts"]) for m in self._meshes)

    def mesh_vertices(self, d: int) -> np.ndarray:
        """(V,) VERTEX_DTYPE: mesh d's vertex records as the GPU holds them (its own buffer, or its part
        of the GPU path's shared one)."""
        mesh = self._meshes[d]
        if mesh["vbo"] is not None:
            return np.frombuffer(mesh["vbo"].read(), VERTEX_DTYPE)
        end = self._meshes[d + 1]["base_vertex"] if d + 1 < len(self._meshes) else None
        return np.frombuffer(self._merged["vbo"].read(), VERTEX_DTYPE)[mesh["base_vertex"]:end]

    def _render_pass(self, kind: str, cascade: int = 0) -> None:
        """Every (weapon, LOD) mesh of a pass: one multi-draw on the GPU path, a draw per mesh with
        instances on the CPU path."""
        if self.feedback_cull:
            for d, mesh in enumerate(self._meshes):
                if mesh["shadow_counts"][cascade] if kind == "depth" else mesh["count"]:
                    self._counter.draw(self._vao(mesh, kind, cascade if kind == "depth" else 0), d + ((1 + cascade) * len(self._meshes) if kind == "depth" else 0))
            return
        if self.gpu_cull:
            if not any(m["shadow_counts"][cascade] if kind == "depth" else m["count"] for m in self._meshes):
                return
            commands = self._shadow_commands if kind == "depth" else self._commands
            first = cascade * len(self._meshes) if kind == "depth" else 0
            self._vao(self._merged, kind).render_indirect(commands, moderngl.TRIANGLES, count=len(self._meshes), first=first)
            return
        for mesh in self._meshes:
            count = mesh["shadow_counts"][cascade] if kind == "depth" else mesh["count"]
            if count:
                self._vao(mesh, kind, cascade if kind == "depth" else 0).render(moderngl.TRIANGLES, instances=count)

    def grip_points(self, frames: AgentFrames) -> np.ndarray:
        """(K, 3) float64: the grip point of each drawn weapon, through the float32 model-space rows the
        GPU got, placed by `frames` as weapon.vert.glsl places them."""
        agents, weapon, rows = self.drawn
        return frames.points(agents, np.einsum("kij,kj->ki", rows.astype(np.float64), self._grip_in_socket[weapon]))

    def depth_pass(self, view, renderer) -> None:
        """Into each shadow cascade's tile (``renderer.shadow_tiles``), after the crowd's shadow pass."""
        prog = self._programs["depth"]
        for k, matrix in renderer.shadow_tiles(view):
            set_uniforms(prog, u_view_proj=gl_bytes(matrix))
            self._render_pass("depth", k)

    def color_pass(self, framebuffer, view, renderer) -> None:
        """`view`: this frame's ``FrameView``; `renderer` lights the weapons as it lights the crowd."""
        framebuffer.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        renderer.bind_shadow_map()  # (the camera and the light: the frame block)
        self._render_pass("color")

    def gpu_bytes(self) -> int:
        return self._objects.gpu_bytes()

    def release(self) -> None:
        if getattr(self, "_ring", None) is not None:
            self._ring.drop()
        if getattr(self, "_counter", None) is not None:
            self._counter.ring.drop()
        self._objects.release()
        self._meshes = []
