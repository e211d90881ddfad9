"""What bounds the skinned instanced draw? Times the same crowd under two vertex layouts and several
skinning variants, side by side in one run, and writes the table behind docs/BENCHMARKS.md's
"Vertex layout" section.

    python -m bench.vertex_layout_probe [--agents 16384] [--frames 6] [--json out.json]

Layouts: "separate" is the first renderer's (5 vertex + 4 instance attributes: position, normal,
joints, weights, colour; position, yaw/scale, palette, tint); "packed" is the demo's (position + one
uvec4 per vertex, vec4 + uvec3 per instance; crowd/draw/render.py). Every agent at LOD0, no culling; all
draws read the same processed palette. Run it where timings mean something (the H100).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import moderngl
import numpy as np

from crowd.draw.frame_block import FRAME_DEFINES, use_frame_block
from crowd.gl import Offscreen, describe, headless_context, load_shader
from crowd.asset.gltf import load_character
from crowd.files import atomic_write_bytes
from .common import grid_crowd, random_layers
from crowd.frame import Instances
from crowd.draw.cull_lists import RECORD_DTYPE, entry_agents
from crowd.draw.packing import VERTEX_DTYPE, VERTEX_FORMAT
from crowd.draw.packing import read_by as _read_by
from crowd.draw.view import gl_bytes
from crowd.anim.roles import bake_roles, match_roles
from crowd.settings import parse
from crowd.stages import StageSpec, Stages

# The packed variant's instances: each agent's record as attributes (the layout measured on the H100, before
# the draws fetched records through a buffer texture).
INSTANCE_FORMAT = ("4f 3u 4x/i", "i_position_scale", "i_packed")
SEPARATE_VERTEX = np.dtype([("position", "<f4", 3), ("normal", "<f2", 4), ("joints", "u1", 4), ("weights", "<f2", 4), ("color", "u1", 4)])
SEPARATE_VERTEX_FORMAT = ("3f 4f2 4u1 4f2 4f1", "in_position", "in_normal", "in_joints", "in_weights", "in_color")
SEPARATE_INSTANCE = np.dtype([("position", "<f4", 3), ("yaw_scale", "<f4", 2), ("palette", "<u2", 2), ("tint", "u1", 4)])
SEPARATE_INSTANCE_FORMAT = ("3f 2f 2u2 4f1/i", "i_position", "i_yaw_scale", "i_palette", "i_tint")
VARIANTS = {  # name: (layout, define or None, palette)
    "separate skinned": ("SEPARATE", None, "f32"),
    "separate unskinned": ("SEPARATE", "UNSKINNED", "f32"),
    "separate unskinned, reads joints+weights": ("SEPARATE", "UNSKINNED_READS_JOINTS", "f32"),
    "separate one bone (weights unread)": ("SEPARATE", "ONE_BONE", "f32"),
    "separate four bones, no branch": ("SEPARATE", "FOUR_BONES", "f32"),
    "separate skinned, RGBA16F palette": ("SEPARATE", None, "f16"),
    "packed skinned": ("PACKED", None, "f32"),
    "packed unskinned": ("PACKED", "UNSKINNED", "f32"),
    "packed unskinned, reads joints+weights": ("PACKED", "UNSKINNED_READS_JOINTS", "f32"),
    "packed one bone": ("PACKED", "ONE_BONE", "f32"),
    "packed four bones, no branch": ("PACKED", "FOUR_BONES", "f32"),
}


def separate_vertices(packed: np.ndarray, mesh) -> np.ndarray:
    """The first renderer's vertex records for the same mesh (float weights and normals as half floats)."""
    v = np.zeros(len(packed), SEPARATE_VERTEX)
    v["position"] = mesh.positions
    v["normal"][:, :3] = mesh.normals
    order = np.argsort(-mesh.weights, axis=1, kind="stable")
    w = np.take_along_axis(mesh.weights, order, axis=1)
    v["joints"] = np.take_along_axis(mesh.joints, order, axis=1)
    v["weights"] = w / w.sum(axis=1, keepdims=True)
    v["color"] = (packed["packed"][:, 3:4] >> np.array([0, 8, 16, 24], np.uint32)) & 0xFF
    return v


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--agents", type=int, default=16384)
    p.add_argument("--frames", type=int, default=6)
    p.add_argument("--size", default="1920x1080")
    p.add_argument("--json")
    args = p.parse_args(argv)
    size = parse("size", args.size)
    ctx = headless_context()
    info = describe(ctx)
    character = load_character(None)
    roles, _ = match_roles(character.clips)
    baked = bake_roles(character, roles)
    spec = StageSpec(lod_distances=(1e9, 1e9, 1e9), shadows=False, culling=False, cull="cpu")  # counts at once, its own instance buffers
    own: list = []  # the probe's own programs, buffers and arrays, released however the run ends
    with Stages.build(ctx, (character, baked), spec, args.agents) as stages, Offscreen(ctx, size) as target:
        proc, renderer, fb = stages.processor, stages.renderer, target.framebuffer
        half_planes = []
        try:
            n = args.agents
            rng = np.random.default_rng(1)
            layers = random_layers(n, 4, len(baked.clips), rng)
            proc.process(layers)
            if proc.slot_layers * proc.history != 1:
                raise SystemExit(f"the probe's shader reads layer 0 only: {n:,} agents need {proc.slot_layers * proc.history} palette layers")
            for plane in proc.planes:
                data = np.frombuffer(plane.read(), np.float32).astype(np.float16)
                tex = ctx.texture_array(plane.size, 4, data.tobytes(), dtype="f2")
                tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
                half_planes.append(tex)
                own.append(tex)

            pos, camera = grid_crowd(n, size[0] / size[1])
            yaw = rng.uniform(-3, 3, n).astype(np.float32)
            instances = Instances(pos, yaw, np.ones(n, np.float32), np.full((n, 4), 200, np.uint8), {"head": np.zeros(n, int)})
            view_proj = renderer.prepare(camera, instances).view_proj
            draws = [d for d in renderer.draws if d.count]
            records = np.frombuffer(renderer.records.buffer.read(), RECORD_DTYPE)
            listed = {id(d): records[entry_agents(renderer.listed(k))[0]] for k, d in enumerate(renderer.draws) if d.count}
            meshes = {(m.piece, m.lod): m for m in character.meshes}
            sep_inst = np.zeros(n, SEPARATE_INSTANCE)
            sep_inst["position"] = pos - camera.eye
            sep_inst["yaw_scale"][:, 0] = yaw
            sep_inst["yaw_scale"][:, 1] = 1.0
            agent = np.arange(n)
            sep_inst["palette"][:, 0], sep_inst["palette"][:, 1] = proc.layout.texel(agent, 0)
            sep_inst["tint"] = 200
            own.append(ctx.buffer(sep_inst.tobytes()))
            sep_buffer = own[-1]
            query = ctx.query(time=True)

            vaos = {}
            for name, (layout, define, _) in VARIANTS.items():
                defines = {layout: 1} | ({define: 1} if define else {})
                prog = ctx.program(vertex_shader=load_shader("bench/vertex_layout.vert.glsl", defines),
                                   fragment_shader=load_shader("skin.frag.glsl", FRAME_DEFINES))
                use_frame_block(prog)  # (its light: the renderer's frame block, written by prepare above)
                own.append(prog)
                for uniform, unit in (("u_palette0", 0), ("u_palette1", 1), ("u_palette2", 2)):
                    if uniform in prog:
                        prog[uniform] = unit
                prog["u_view_proj"].write(gl_bytes(view_proj))
                vaos[name] = []
                for draw in draws:
                    if layout == "PACKED":
                        own.append(ctx.buffer(listed[id(draw)].tobytes()))
                        content = [(draw.vbo, *_read_by(prog, VERTEX_FORMAT)), (own[-1], *_read_by(prog, INSTANCE_FORMAT))]
                    else:
                        packed = np.frombuffer(draw.vbo.read(), VERTEX_DTYPE)
                        vbo = ctx.buffer(separate_vertices(packed, meshes[(draw.piece, draw.lod)]).tobytes())
                        own.append(vbo)
                        content = [(vbo, *_read_by(prog, SEPARATE_VERTEX_FORMAT)), (sep_buffer, *_read_by(prog, SEPARATE_INSTANCE_FORMAT))]
                    vao = ctx.vertex_array(prog, content, index_buffer=draw.ibo, index_element_size=4)
                    own.append(vao)
                    vaos[name].append(vao)

            triangles = renderer.last["triangles"]
            samples = {name: [] for name in VARIANTS}
            for frame in range(args.frames + 2):
                for name, (_, _, palette) in VARIANTS.items():
                    fb.use()
                    fb.clear(0.1, 0.1, 0.1, 1.0, depth=1.0)
                    ctx.enable(moderngl.DEPTH_TEST)
                    ctx.disable(moderngl.CULL_FACE)
                    if palette == "f16":
                        for unit, tex in enumerate(half_planes):
                            tex.use(unit)
                    else:
                        proc.bind_palette(0)
                    with query:
                        for vao in vaos[name]:
                            vao.render(moderngl.TRIANGLES, instances=n)
                    if frame >= 2:  # the first frames compile and upload
                        samples[name].append(query.elapsed / 1e6)
            print(f"{info['gl_renderer']} | {info['gl_version']} | {size[0]}x{size[1]} | {n} agents at LOD0, {triangles:,} triangles | median of {args.frames} frames")
            rows = []
            for name in VARIANTS:
                ms = float(np.median(samples[name]))
                rows.append({"variant": name, "draw_ms": round(ms, 3), "tris_per_s": round(triangles / (ms / 1e3))})
                print(f"  {name:44s} {ms:9.2f} ms {triangles / ms / 1e3:8.0f} Mtri/s")
            if args.json:
                atomic_write_bytes(Path(args.json), json.dumps({"device": f"{info['gl_renderer']}, {info['gl_version']}", "agents": n,
                                                                "triangles": triangles, "size": list(size), "rows": rows}, indent=1).encode())
        finally:
            for obj in reversed(own):
                obj.release()
    ctx.release()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
