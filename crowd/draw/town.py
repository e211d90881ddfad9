"""The town's draw stage: the buildings, cars, barriers and kerbs of crowd.asset.town, one instanced draw
per mesh in the colour pass and per shadow cascade, lit, shadowed and fogged as the crowd is.

Contract: ``prepare(view)`` after the crowd's ``prepare`` (it takes that FrameView: the camera, its
matrix and the sun's cascades), then ``depth_pass(view, renderer)`` into each cascade's tile after the
crowd's shadow pass, and ``color_pass(framebuffer, view, renderer)``, before the ground. ``prepare``
places the district's pieces in every district within sight of the camera (the town repeats), culls
each placement's sphere against the view (and each cascade's box, for its shadow), and uploads the
kept ones per mesh: a few thousand placements for the largest world, in numpy.

Positions are camera-relative, as the crowd's: the CPU subtracts the eye in float64. The stage exists
only when the scene has a town (``town`` setting); without it there is no mesh, buffer or pass.
"""

from __future__ import annotations

import moderngl
import numpy as np

from ..asset.town import PERIOD, TINTS, Town
from ..gl import GLObjects, GLStage, load_shader, set_uniforms
from .cpu_cull import sphere_visible
from .packing import write_heading
from .draw_programs import fixed_units, lighting_defines
from .frame_block import FRAME_DEFINES
from .view import frustum_planes, gl_bytes
from .shadows import CASCADES
from .weapons import pack_rigid

INSTANCE_DTYPE = np.dtype([("position", "<f4", 3), ("fields", "<u4", 2)])  # town.vert.glsl's i_position, i_fields
SIGHT_M = 800.0  # metres from the eye within which districts are placed: the fog has hidden the rest (crowd.lighting)


class TownRenderer(GLStage):
    """Owns the town's meshes, instance buffers and programs."""

    def __init__(self, ctx: moderngl.Context, town: Town, shadows: bool, gpu_cull: bool = False):
        """`gpu_cull`: cull the placements on the GPU (GL 4.3: the crowd's compute cull path) rather than in numpy."""
        self._objects = GLObjects()
        self.ctx = ctx
        self.town = town
        self.shadows = shadows
        self.gpu_cull = bool(gpu_cull)
        self._passes = 1 + (CASCADES if shadows else 0)
        self._pieces = []
        for piece in town.pieces:
            vertices = pack_rigid(piece.mesh, np.eye(4))
            positions = np.asarray(piece.mesh.positions, np.float64)
            self._pieces.append({
                "piece": piece, "triangles": piece.mesh.triangle_count,
                "vbo": self._objects.add(ctx.buffer(vertices.tobytes())),
                "ibo": self._objects.add(ctx.buffer(np.ascontiguousarray(piece.mesh.indices, np.uint32).tobytes())),
                "instances": self._objects.add(ctx.buffer(reserve=INSTANCE_DTYPE.itemsize)),
                "shadow_instances": [self._objects.add(ctx.buffer(reserve=INSTANCE_DTYPE.itemsize)) for _ in range(CASCADES)]
                if shadows and piece.casts_shadow else [],
                "count": 0, "shadow_counts": [0] * CASCADES, "vaos": {},
                # A sphere about the placement's origin that holds the mesh whatever its heading.
                "radius": float(np.max(np.linalg.norm(positions, axis=1))),
            })
        defines = lighting_defines(shadows)
        self._programs = {
            "color": self._objects.add(ctx.program(vertex_shader=load_shader("town.vert.glsl", FRAME_DEFINES), fragment_shader=load_shader("skin.frag.glsl", defines))),
            "depth": self._objects.add(ctx.program(vertex_shader=load_shader("town.vert.glsl", {"DEPTH_ONLY": 1}),
                                                   fragment_shader=load_shader("depth.frag.glsl"))),
        }
        fixed_units(self._programs["color"])
        if self.gpu_cull:
            self._programs["cull"] = self._objects.add(ctx.compute_shader(load_shader("town_cull.comp.glsl", {"PASSES": self._passes})))
        self.height = max(float(np.max(np.asarray(p.mesh.positions)[:, 1])) for p in town.pieces)  # the tallest roof
        self._last = {"instances": 0, "triangles": 0, "shadow_instances": 0, "draws": 0}
        self._placed_for: dict | None = None  # _place's districts in sight and what was placed there
        self._gpu: dict | None = None  # the GPU cull's buffers for _placed_for (gpu_cull)
        self._anchor_rel = (0.0, 0.0, 0.0)  # where the instances count from, relative to the camera

    def _vao(self, piece: dict, kind: str, cascade: int = 0) -> moderngl.VertexArray:
        if (kind, cascade) not in piece["vaos"]:
            prog = self._programs[kind]
            vertex = ("3f 2u", "in_position", "in_packed") if kind == "color" else ("3f 8x", "in_position")
            if self.gpu_cull:  # (each piece's instances in its region of its pass's buffer: the command's base instance)
                instances = self._gpu["out"][1 + cascade if kind == "depth" else 0]
            else:
                instances = piece["shadow_instances"][cascade] if kind == "depth" else piece["instances"]
            instance = ("3f 2u/i", "i_position", "i_fields")
            piece["vaos"][kind, cascade] = self._objects.add(self.ctx.vertex_array(
                prog, [(piece["vbo"], *vertex), (instances, *instance)], index_buffer=piece["ibo"], index_element_size=4))
        return piece["vaos"][kind, cascade]

    # -- per frame

    @staticmethod
    def _districts(eye: np.ndarray, sight: float = SIGHT_M) -> tuple[int, int, int, int]:
        """The district indices (x from, z from, x to, z to) within `sight` metres of the eye."""
        lo = np.floor((eye[[0, 2]] - sight) / PERIOD).astype(np.int64)
        hi = np.floor((eye[[0, 2]] + sight) / PERIOD).astype(np.int64)
        return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])

    @staticmethod
    def _placed(districts: tuple[int, int, int, int], piece) -> np.ndarray:
        """(K, 4) float64 placements of `piece` (x, z, yaw, tint) in these districts."""
        x0, z0, x1, z1 = districts
        dx, dz = np.meshgrid(np.arange(x0, x1 + 1) * PERIOD, np.arange(z0, z1 + 1) * PERIOD, indexing="ij")
        offsets = np.stack([dx.ravel(), dz.ravel()], axis=1)
        p = piece.placements
        out = np.repeat(p[None], len(offsets), axis=0)
        out[..., 0] += offsets[:, 0, None]
        out[..., 1] += offsets[:, 1, None]
        return out.reshape(-1, 4)

    def _place(self, eye: np.ndarray, sight: float = SIGHT_M) -> dict:
        """Every piece's placements in sight, piece after piece, with their radii and records' constant fields.
        They change only when the eye crosses into another district's reach, so they are kept until then
        (placing and packing them each frame was most of the stage's CPU time)."""
        districts = self._districts(eye, sight)
        if self._placed_for is not None and self._placed_for["districts"] == districts:
            return self._placed_for
        parts = [self._placed(districts, piece["piece"]) for piece in self._pieces]
        counts = np.array([len(part) for part in parts])
        placed = np.concatenate(parts)
        records = np.zeros(len(placed), INSTANCE_DTYPE)
        write_heading(placed[:, 2], records["fields"][:, 0])
        records["fields"][:, 1] = TINTS[placed[:, 3].astype(np.int64)].view("<u4")[:, 0]
        # Each district's bounding sphere, culled first: only the placements of districts in view are tested.
        x0, z0, x1, z1 = districts
        dx, dz = np.meshgrid(np.arange(x0, x1 + 1) * PERIOD, np.arange(z0, z1 + 1) * PERIOD, indexing="ij")
        # The district's sphere holds every placement's sphere (they are centred on the ground, as the
        # placements are culled): centred among the placements, its radius the farthest one's reach.
        local = np.concatenate([piece["piece"].placements[:, :2] for piece in self._pieces])
        radii = np.concatenate([np.full(len(piece["piece"].placements), piece["radius"]) for piece in self._pieces])
        middle = (local.min(axis=0) + local.max(axis=0)) / 2
        district_radius = float(np.max(np.hypot(*(local - middle).T) + radii))
        centres = np.zeros((dx.size, 3))
        centres[:, 0], centres[:, 2] = dx.ravel() + middle[0], dz.ravel() + middle[1]
        self._placed_for = {
            "districts": districts, "xz": placed[:, :2], "records": records, "bounds": np.concatenate([[0], np.cumsum(counts)]),
            "radius": np.repeat([piece["radius"] for piece in self._pieces], counts),
            "casts": np.repeat([bool(piece["shadow_instances"]) for piece in self._pieces], counts),
            "district": np.concatenate([np.repeat(np.arange(dx.size), len(piece["piece"].placements)) for piece in self._pieces]),
            "centres": centres, "district_radius": district_radius,
        }
        return self._placed_for

    @property
    def last(self) -> dict:
        """The last frame's instances, triangles, shadow instances and draws (on the GPU cull path read back
        from its commands: synchronous, for stats and tests)."""
        if self.gpu_cull and self._gpu is not None:
            counts = np.frombuffer(self._gpu["commands"].read(), np.uint32).reshape(self._passes, len(self._pieces), 5)[:, :, 1].astype(np.int64)
            triangles = np.array([piece["triangles"] for piece in self._pieces], np.int64)
            return {"instances": int(counts[0].sum()), "triangles": int(counts[0] @ triangles),
                    "shadow_instances": int(counts[1:].sum()), "draws": int(np.count_nonzero(counts[0]))}
        return self._last

    def prepare(self, view) -> None:
        """Cull this frame's placements: the view's, and each shadow cascade's (with shadows). All pieces'
        placements are culled together: on the GPU, one pass over the districts in sight into each pass's
        instances and indirect commands; in numpy, districts first, then the placements of those in view,
        uploaded piece by piece."""
        eye = np.asarray(view.camera.eye, np.float64)
        placed = self._place(eye, max(SIGHT_M, view.camera.fog_reach or 0.0))  # a thinned fog sees further (the horizon view)
        if self.gpu_cull:
            self._cull_on_gpu(view, placed, eye)
            return
        records, radius, bounds = placed["records"], placed["radius"], placed["bounds"]
        rel = np.empty((len(records), 3))
        rel[:, 0], rel[:, 1], rel[:, 2] = placed["xz"][:, 0] - eye[0], -eye[1], placed["xz"][:, 1] - eye[2]
        records["position"] = rel
        centres = placed["centres"] - eye
        centre_edge = np.sqrt(np.einsum("ij,ij->i", centres, centres)) - placed["district_radius"]
        district_radius = np.full(len(centres), placed["district_radius"])

        def kept(matrix, reach, among=None):
            planes = frustum_planes(matrix)
            districts = sphere_visible(planes, centres, district_radius) & (centre_edge <= reach)
            candidates = np.flatnonzero(districts[placed["district"]] & (True if among is None else among))
            near = rel[candidates]
            near_edge = np.sqrt(np.einsum("ij,ij->i", near, near)) - radius[candidates]
            out = np.zeros(len(records), bool)
            out[candidates] = sphere_visible(planes, near, radius[candidates]) & (near_edge <= reach)
            return out

        seen = kept(view.view_proj, view.camera.far)
        casts = [kept(matrix, reach, placed["casts"]) for matrix, reach in zip(view.shadow.view_proj, view.shadow.reach_m)] \
            if view.shadow is not None else []
        total, triangles, shadowed, draws = 0, 0, 0, 0
        for i, piece in enumerate(self._pieces):
            a, b = bounds[i], bounds[i + 1]
            piece["count"] = self._upload(piece["instances"], records[a:b][seen[a:b]])
            total += piece["count"]
            triangles += piece["count"] * piece["triangles"]
            draws += int(piece["count"] > 0)
            for k, shadow in enumerate(piece["shadow_instances"]):
                piece["shadow_counts"][k] = self._upload(shadow, records[a:b][casts[k][a:b]]) if k < len(casts) else 0
                shadowed += piece["shadow_counts"][k]
        self._last = {"instances": total, "triangles": triangles, "shadow_instances": shadowed, "draws": draws}

    def _cull_on_gpu(self, view, placed: dict, eye: np.ndarray) -> None:
        if self._gpu is None or self._gpu["placed"] is not placed:
            self._gpu_buffers(placed)
        g = self._gpu
        self._anchor_rel = tuple(float(v) for v in g["anchor"] - eye)
        if not g["count"]:
            return
        self.ctx.copy_buffer(g["commands"], g["template"])
        matrices = [view.view_proj] + (list(view.shadow.view_proj) if self._passes > 1 else [])
        reach = [view.camera.far] + (list(view.shadow.reach_m) if self._passes > 1 else [])
        prog = self._programs["cull"]
        prog["u_planes"].write(np.concatenate([frustum_planes(m) for m in matrices]).astype(np.float32).tobytes())
        prog["u_reach"].write(np.asarray(reach, np.float32).tobytes())
        set_uniforms(prog, u_count=g["count"], u_pieces=len(self._pieces), u_anchor_rel=self._anchor_rel)
        for binding, buffer in enumerate((g["records"], g["info"], g["commands"], *g["out"])):
            buffer.bind_to_storage_buffer(binding)
        prog.run((g["count"] + 63) // 64)
        self.ctx.memory_barrier(moderngl.COMMAND_BARRIER_BIT | moderngl.VERTEX_ATTRIB_ARRAY_BARRIER_BIT)

    def _gpu_buffers(self, placed: dict) -> None:
        """The GPU cull's buffers for the districts in sight: every placement (from the districts' anchor,
        float32: within a kilometre of it), its sphere's radius and piece, each pass's instances in regions
        by piece, and the commands' template (each piece's region as its base instance)."""
        self._release_gpu()
        x0, z0 = placed["districts"][:2]
        anchor = np.array([x0 * PERIOD, 0.0, z0 * PERIOD])
        records = placed["records"].copy()
        records["position"][:, 0] = placed["xz"][:, 0] - anchor[0]
        records["position"][:, 1] = 0.0
        records["position"][:, 2] = placed["xz"][:, 1] - anchor[2]
        bounds = placed["bounds"]
        piece = np.repeat(np.arange(len(self._pieces), dtype=np.uint32), np.diff(bounds))
        info = np.stack([placed["radius"].astype(np.float32).view(np.uint32), piece | (placed["casts"].astype(np.uint32) << 16)], axis=1)
        template = np.zeros((self._passes, len(self._pieces), 5), np.uint32)
        template[:, :, 0] = [p["triangles"] * 3 for p in self._pieces]
        template[:, :, 4] = bounds[:-1]
        size = max(records.nbytes, INSTANCE_DTYPE.itemsize)
        objects = GLObjects()
        try:
            self._gpu = {"placed": placed, "anchor": anchor, "count": len(records),
                         "records": objects.add(self.ctx.buffer(records.tobytes() or bytes(INSTANCE_DTYPE.itemsize))),
                         "info": objects.add(self.ctx.buffer(info.tobytes() or bytes(8))),
                         "template": objects.add(self.ctx.buffer(template.tobytes())),
                         "commands": objects.add(self.ctx.buffer(template.tobytes())),
                         "out": [objects.add(self.ctx.buffer(reserve=size)) for _ in range(self._passes)], "objects": objects}
        except BaseException:
            objects.release()
            self._gpu = None
            raise

    def _release_gpu(self) -> None:
        """The GPU cull's buffers and the vertex arrays that read them."""
        if self._gpu is None:
            return
        for piece in self._pieces:
            for vao in piece["vaos"].values():
                self._objects.remove(vao)
                vao.release()
            piece["vaos"] = {}
        self._gpu["objects"].release()
        self._gpu = None

    @staticmethod
    def _upload(buffer: moderngl.Buffer, records: np.ndarray) -> int:
        size = max(records.nbytes, INSTANCE_DTYPE.itemsize)
        if buffer.size != size:
            buffer.orphan(size)
        if len(records):
            buffer.write(records.tobytes())
        return len(records)

    def depth_pass(self, view, renderer) -> None:
        """Into each shadow cascade's tile (``renderer.shadow_tiles``), after the crowd's shadow pass."""
        prog = self._programs["depth"]
        set_uniforms(prog, u_anchor_rel=self._anchor_rel)
        for k, matrix in renderer.shadow_tiles(view):
            set_uniforms(prog, u_view_proj=gl_bytes(matrix))
            for i, piece in enumerate(self._pieces):
                if self.gpu_cull:
                    if piece["piece"].casts_shadow and self._gpu is not None and self._gpu["count"]:
                        self._vao(piece, "depth", k).render_indirect(self._gpu["commands"], moderngl.TRIANGLES, count=1,
                                                                     first=(1 + k) * len(self._pieces) + i)
                elif piece["shadow_instances"] and piece["shadow_counts"][k]:
                    self._vao(piece, "depth", k).render(moderngl.TRIANGLES, instances=piece["shadow_counts"][k])

    def color_pass(self, framebuffer, view, renderer) -> None:
        """`view`: this frame's FrameView; `renderer` lights the town as it lights the crowd."""
        framebuffer.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        prog = self._programs["color"]
        set_uniforms(prog, u_anchor_rel=self._anchor_rel)
        renderer.bind_shadow_map()  # (the camera and the light: the frame block)
        for i, piece in enumerate(self._pieces):
            if self.gpu_cull:
                if self._gpu is not None and self._gpu["count"]:
                    self._vao(piece, "color").render_indirect(self._gpu["commands"], moderngl.TRIANGLES, count=1, first=i)
            elif piece["count"]:
                self._vao(piece, "color").render(moderngl.TRIANGLES, instances=piece["count"])

    def gpu_bytes(self) -> int:
        return self._objects.gpu_bytes() + (self._gpu["objects"].gpu_bytes() if self._gpu is not None else 0)

    def release(self) -> None:
        self._release_gpu()
        self._objects.release()
        self._pieces = []
