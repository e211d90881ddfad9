"""The crowd renderer's programs, built from shaders/ with the defines a scene needs: the skinned pieces'
(colour, depth and the impostor bake's), the impostors' and the ground's. Features a scene does not use
are compiled out, not branched around (crowd.gl.load_shader)."""

from __future__ import annotations

import moderngl

from ..asset.town import SIDEWALK, STREET, TILE
from ..gl import has_uniform, load_shader
from .frame_block import FRAME_DEFINES, use_frame_block
from .materials import TEXTURE_UNIT
from .records import use_records_unit


def lighting_defines(shadows: bool) -> dict:
    """lighting.glsl's defines: the frame block's (frame.glsl), and shadows where the scene has them."""
    return {**FRAME_DEFINES, "SHADOWS": 1} if shadows else dict(FRAME_DEFINES)


def fixed_units(prog):
    """`prog`'s samplers that always read one texture unit (the palette's, the shadow map's, the
    material's and the records'), and its frame block's binding. Returns it."""
    for name, unit in (("u_palette0", 0), ("u_palette1", 1), ("u_palette2", 2), ("u_shadow_map", 3), ("u_albedo", TEXTURE_UNIT)):
        if has_uniform(prog, name):
            prog[name] = unit
    use_records_unit(prog)
    use_frame_block(prog)
    return prog


def draw_program(ctx: moderngl.Context, kind: str, skinned: bool | str, layout: str = "", morph: bool = False, *, shadows: bool,
                 lod_fade: bool, town: bool, morph_buffers: bool, unlit: bool = False) -> moderngl.Program:
    """kind: color, depth, bake or ground; skinned: True, or False for the benchmark's unskinned ceiling;
    layout: a textured piece's vertex layout ("packed" or "wide", crowd.draw.packing.uv_layout), "impostor",
    or "" for none; morph: pieces drawn with their morph targets (`morph_buffers`: their deltas in storage
    buffers); `lod_fade`: LODs cross-fade; `town`: the ground shows the town's streets; `unlit` (colour
    programs): the pieces say whether they are KHR_materials_unlit, or an impostor's character is."""
    defines = lighting_defines(shadows)
    if lod_fade and kind == "color":
        defines["LOD_FADE"] = 1
    if unlit and kind == "color":
        defines["UNLIT" if layout == "impostor" else "UNLIT_PIECES"] = 1
    if kind == "ground":
        if town:
            defines["TOWN"] = 1
        prog = ctx.program(vertex_shader=load_shader("ground.vert.glsl", FRAME_DEFINES), fragment_shader=load_shader("ground.frag.glsl", defines))
        if town:
            prog["u_tile"], prog["u_street"], prog["u_sidewalk"] = TILE, STREET, SIDEWALK
    elif layout == "impostor":
        vdefs = {"DEPTH_ONLY": 1} if kind == "depth" else dict(FRAME_DEFINES)
        prog = ctx.program(vertex_shader=load_shader("impostor.vert.glsl", vdefs),
                       fragment_shader=load_shader("impostor.frag.glsl", {**defines, **vdefs}))
    else:
        vdefs = dict(FRAME_DEFINES) if skinned else {**FRAME_DEFINES, "UNSKINNED": 1}
        if "LOD_FADE" in defines:
            vdefs["LOD_FADE"] = 1
        if kind == "depth":
            vdefs["DEPTH_ONLY"] = 1
            frag = load_shader("depth.frag.glsl")
        else:
            if layout:
                defines["TEXTURED"] = 1
            if kind == "bake":  # an impostor atlas's cells (crowd.draw.impostors): unlit, no shadows
                defines = {k: v for k, v in defines.items() if k != "SHADOWS"}
                defines["IMPOSTOR_BAKE"] = vdefs["IMPOSTOR_BAKE"] = 1
            frag = load_shader("skin.frag.glsl", defines)
        if layout:
            vdefs["TEXTURED"] = 1
        if layout == "wide":
            vdefs["WIDE_UV"] = 1
        if "UNLIT_PIECES" in defines:
            vdefs["UNLIT_PIECES"] = 1
        if morph:
            vdefs["MORPH"] = 1
            if morph_buffers:
                vdefs["MORPH_BUFFERS"] = 1
        prog = ctx.program(vertex_shader=load_shader("skin.vert.glsl", vdefs), fragment_shader=frag)
    return fixed_units(prog)
