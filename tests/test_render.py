"""Skinned instancing against float64 skinning: what the vertex shader computes, captured with transform
feedback, for every vertex of every piece and agent.

The vertex layout quantises weights (unorm10 of 2w), normals (snorm10) and the heading's cos/sin
(snorm16); each vertex gets its own error bound from those steps, so a wrong decode (a bit field off,
a sign lost) fails at once while the rounding the layout is designed for passes.
"""

from __future__ import annotations

import moderngl
import numpy as np

from crowd.draw.frame_block import FRAME_BINDING, FRAME_DEFINES, use_frame_block
from crowd.anim.bake import bake
from crowd.gl import load_shader
from crowd.frame import CLIP, PHASE, WEIGHT, empty_layers
from crowd.anim.processor import AnimationProcessor
from crowd.anim.palette_reference import reference_palette
from crowd.draw.cull_lists import entry_agents
from crowd.draw.packing import VERTEX_DTYPE, VERTEX_FORMAT, WEIGHT_STEP, pack_vertices, read_by, unpack_weights
from crowd.draw.records import use_records_unit
from crowd.draw.render import ENTRY_FORMAT, CrowdRenderer
from crowd.frame import Camera, Instances

AGENTS = 9


def test_packed_weights_decode_to_the_float_weights(zombie):
    for mesh in zombie.meshes:
        packed = pack_vertices(mesh)
        decoded = unpack_weights(packed["packed"][:, 2])
        w = np.sort(mesh.weights.astype(np.float64), axis=1)[:, ::-1]
        w /= w.sum(axis=1, keepdims=True)
        assert np.allclose(decoded.sum(axis=1), 1.0, atol=1e-12)
        assert np.max(np.abs(decoded[:, 1:] - w[:, 1:])) <= 0.5 * WEIGHT_STEP + 1e-12
        assert np.all(decoded >= 0.0)


def capture(ctx, renderer, index, proc, defines=None, setup=None):
    """v_world and v_normal of every vertex of every instance of draw `index` of `renderer` (instance-major),
    through skin.vert.glsl with `defines`; `setup(program)` binds what those need."""
    draw = renderer.draws[index]
    prog = ctx.program(vertex_shader=load_shader("skin.vert.glsl", {**FRAME_DEFINES, **(defines or {})}), varyings=["v_world", "v_normal"])
    for name, unit in (("u_palette0", 0), ("u_palette1", 1), ("u_palette2", 2)):
        prog[name] = unit
    use_records_unit(prog)
    renderer.records.bind()
    proc.bind_palette(0, prog)
    if setup is not None:
        setup(prog)
    # (gl_Position is not captured: the frame block's camera is what the renderer last wrote, bound as the draws have it)
    use_frame_block(prog)
    renderer.frame_block.buffer.bind_to_uniform_block(FRAME_BINDING)
    vao = ctx.vertex_array(prog, [(draw.vbo, *read_by(prog, VERTEX_FORMAT)), (renderer._entries(index, None), *read_by(prog, ENTRY_FORMAT))])
    vertices = draw.vbo.size // VERTEX_DTYPE.itemsize
    out = ctx.buffer(reserve=vertices * draw.count * 6 * 4)
    # A standalone context has no default framebuffer, and Mesa refuses even a rasteriser-discarded draw
    # without a complete one.
    target = ctx.simple_framebuffer((1, 1))
    target.use()
    vao.transform(out, moderngl.POINTS, vertices=vertices, instances=draw.count)
    target.release()
    data = np.frombuffer(out.read(), np.float32).reshape(draw.count, vertices, 2, 3).astype(np.float64)
    for obj in (out, vao, prog):
        obj.release()
    return data[:, :, 0], data[:, :, 1]


def test_gpu_skinned_vertices_match_float64_skinning(gl_context, zombie):
    ctx = gl_context
    baked = bake(zombie.skeleton, zombie.clips)
    rng = np.random.default_rng(4)
    layers = empty_layers(AGENTS, 4)
    layers[..., CLIP] = rng.integers(0, len(baked.clips), (AGENTS, 4))
    layers[..., PHASE] = rng.uniform(0, 1, (AGENTS, 4))
    layers[..., WEIGHT] = rng.uniform(0.1, 1.0, (AGENTS, 4))
    proc = AnimationProcessor(ctx, baked, 4)
    proc.resize(AGENTS)
    proc.process(layers)
    palette = reference_palette(baked, layers)  # (N, J, 3, 4) float64
    renderer = CrowdRenderer(ctx, zombie, lod_distances=(1e6, 2e6, 3e6), shadows=False, culling=False)
    positions = np.column_stack([rng.uniform(-30, 30, AGENTS), np.zeros(AGENTS), rng.uniform(-30, 30, AGENTS)]) + [1e5, 0.0, -2e5]
    yaw = rng.uniform(-np.pi, np.pi, AGENTS).astype(np.float32)
    scale = rng.uniform(0.8, 1.25, AGENTS).astype(np.float32)
    heads = rng.integers(0, len(renderer.groups[0]["head"]), AGENTS)
    instances = Instances(positions, yaw, scale, np.full((AGENTS, 4), 255, np.uint8), {"head": heads})
    camera = Camera(eye=positions.mean(axis=0) + [0.0, 20.0, 40.0], target=positions.mean(axis=0))
    renderer.prepare(camera, instances)
    proc.bind_palette(0)
    meshes = {(m.piece, m.lod): m for m in zombie.meshes}
    checked = 0
    worst = 0.0
    try:
        for index, draw in enumerate(renderer.draws):
            if not draw.count:
                continue
            mesh = meshes[(draw.piece, draw.lod)]
            world, normal = capture(ctx, renderer, index, proc)
            agents = entry_agents(renderer.listed(index))[0]
            w = mesh.weights.astype(np.float64) / mesh.weights.sum(axis=1, keepdims=True)
            p = np.concatenate([mesh.positions.astype(np.float64), np.ones((len(mesh.positions), 1))], axis=1)
            for k, a in enumerate(agents):
                m = palette[a][mesh.joints]  # (V, 4, 3, 4)
                per_bone = np.einsum("vbij,vj->vbi", m, p)  # each influence's transform of the vertex
                skinned = np.einsum("vb,vbi->vi", w, per_bone)
                n = np.einsum("vb,vbij,vj->vi", w, m[..., :3], mesh.normals.astype(np.float64))
                c, s = np.cos(float(yaw[a])), np.sin(float(yaw[a]))
                rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
                expect = positions[a] - camera.eye + float(scale[a]) * skinned @ rot.T
                # Per-vertex bound: each stored weight is within WEIGHT_STEP / 2 (the first weight takes
                # the others' rounding), cos and sin within 0.5 / 32767, plus float32 arithmetic.
                spread = np.linalg.norm(per_bone - per_bone[:, :1], axis=2)
                bound = (0.5 * WEIGHT_STEP * spread.sum(axis=1) * scale[a] + 1.5 / 32767 * np.linalg.norm(skinned, axis=1) * scale[a]
                         + 1e-5)
                err = np.linalg.norm(world[k] - expect, axis=1)
                assert np.all(err <= bound), f"{draw.piece} LOD{draw.lod} agent {a}: {err.max() * 1e3:.4f} mm"
                cos_angle = np.sum(normal[k] * (n @ rot.T), axis=1) / np.linalg.norm(normal[k], axis=1) / np.linalg.norm(n, axis=1)
                assert np.degrees(np.arccos(np.clip(cos_angle.min(), -1, 1))) < 0.5
                worst = max(worst, float(err.max()))
                checked += len(err)
    finally:
        renderer.release()
        proc.release()
    assert checked > AGENTS * 2000  # every LOD0 piece of every agent
    print(f"max skinned vertex error {worst * 1e3:.4f} mm over {checked} vertices")
    assert worst < 2e-4  # 0.2 mm
