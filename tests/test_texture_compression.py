"""Issue 40, point 4: base-colour textures at 2 bytes a texel or less. BC1 with sRGB ends where a
texture's error is within the bound (docs/BENCHMARKS.md, "Textures"), its coarse mip levels in a small
RGBA16F array from the first over the bound, RGBA16F for the textures over it and where the driver
lacks the format; filtering in linear light on every path."""

from __future__ import annotations

import ctypes
import dataclasses

import numpy as np
import pytest

from conftest import shared
from crowd.draw.frame_block import FRAME_DEFINES
from crowd.asset.model import LINEAR, NEAREST, REPEAT, Texture
from crowd.draw import materials, texture_layers
from crowd.draw.materials import BlockArray, MaterialTextures
from crowd.draw.texture_codec import bc1_bytes, ciede2000, colour_difference, decode_bc1, encode_bc1, linear_to_srgb, srgb_to_linear
from crowd.draw.texture_layers import within_bound
from crowd.gl import GLObjects, current_context_function, load_shader

MIPMAPPED = 9987  # LINEAR_MIPMAP_LINEAR


def _opaque(rgb: np.ndarray) -> np.ndarray:
    return np.concatenate([rgb.astype(np.uint8), np.full(rgb.shape[:2] + (1,), 255, np.uint8)], axis=2)


def cells(side: int, cell: int, seed: int = 1) -> np.ndarray:
    """An atlas of flat cells `cell` texels wide, each of one of 64 random colours (Quaternius' atlases
    are such, with 16-texel cells)."""
    colours = np.random.default_rng(seed).integers(0, 256, (64, 3))
    index = (np.arange(side)[:, None] // cell * 7 + np.arange(side)[None, :] // cell * 3) % 64
    return _opaque(colours[index])


def gradient(side: int = 256) -> np.ndarray:
    x = np.linspace(0.0, 255.0, side)
    return _opaque(np.stack(np.broadcast_arrays(x[None, :], x[:, None], np.full((side, side), 128.0)), axis=-1).round())


def noise(side: int = 256) -> np.ndarray:
    return _opaque(np.random.default_rng(2).integers(0, 256, (side, side, 3)))


def ramp() -> np.ndarray:
    """test_textures' 64-texel red-to-green ramp."""
    out = np.zeros((1, 64, 3))
    out[0, :, 0] = np.linspace(0, 255, 64)
    out[0, :, 1] = np.linspace(255, 0, 64)
    return _opaque(out.astype(np.uint8))


FULL_SCREEN = """#version 330
void main() { vec2 p[3] = vec2[](vec2(-1, -1), vec2(3, -1), vec2(-1, 3)); gl_Position = vec4(p[gl_VertexID], 0, 1); }"""

FOUR = _opaque(np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 0]]]))  # test_textures' strip
GENERATED = {"cells 16": lambda: cells(256, 16), "cells 2": lambda: cells(64, 2), "cells 8": lambda: cells(256, 8),
             "gradient": gradient, "noise": noise, "ramp": ramp, "four": lambda: FOUR}
SHARED = ["CesiumMan.glb", "Quaternius_Zombie_Basic.gltf", "Quaternius_Characters_Matt_SingleWeapon.gltf", "Quaternius_CubeWorld_Hedgehog.gltf"]


def source(name: str) -> Texture:
    if name in GENERATED:
        return Texture(name, GENERATED[name](), (REPEAT, REPEAT), LINEAR, MIPMAPPED)
    from crowd.asset.gltf import load_character

    return load_character(shared(name)).textures[0]


def compressed_level(array: BlockArray, level: int) -> np.ndarray:
    """What the driver holds in one level of a BC1 array (every layer's blocks), read back."""
    size = ctypes.c_int(0)
    get_int = current_context_function("glGetTexLevelParameteriv", ctypes.CFUNCTYPE(None, ctypes.c_uint, ctypes.c_int, ctypes.c_uint, ctypes.POINTER(ctypes.c_int)))
    read = current_context_function("glGetCompressedTexImage", ctypes.CFUNCTYPE(None, ctypes.c_uint, ctypes.c_int, ctypes.c_void_p))
    array.use(materials.TEXTURE_UNIT)
    get_int(0x8C1A, level, 0x86A0, ctypes.byref(size))  # TEXTURE_2D_ARRAY, COMPRESSED_IMAGE_SIZE
    out = np.zeros(size.value, np.uint8)
    read(0x8C1A, level, out.ctypes.data)
    return out


def box_levels(linear: np.ndarray, count: int) -> list[np.ndarray]:
    """float64 box-filtered mip levels of a power-of-two image: the test's own reference."""
    levels = [linear]
    while len(levels) < count:
        h, w = levels[-1].shape[:2]
        levels.append(levels[-1].reshape(max(h // 2, 1), h // max(h // 2, 1), max(w // 2, 1), w // max(w // 2, 1), -1).mean(axis=(1, 3)))
    return levels


# -- the codec


def test_ciede2000_agrees_with_sharmas_published_pairs():
    """Pairs 1, 2, 7, 17-20 and 25 of Sharma, Wu and Dalal's test data (2005), to their 4 decimals."""
    pairs = [((50, 2.6772, -79.7751), (50, 0, -82.7485), 2.0425), ((50, 3.1571, -77.2803), (50, 0, -82.7485), 2.8615),
             ((50, 0, 0), (50, -1, 2), 2.3669), ((50, 2.5, 0), (73, 25, -18), 27.1492), ((50, 2.5, 0), (61, -5, 29), 22.8977),
             ((50, 2.5, 0), (56, -27, -3), 31.9030), ((50, 2.5, 0), (58, 24, 15), 19.4535),
             ((60.2574, -34.0099, 36.2677), (60.4626, -34.1751, 39.4387), 1.2644)]
    lab1, lab2, expected = (np.array(x, np.float64) for x in zip(*pairs))
    np.testing.assert_allclose(ciede2000(lab1, lab2), expected, atol=5e-5)
    np.testing.assert_allclose(ciede2000(lab2, lab1), expected, atol=5e-5)  # symmetric


def test_bc1_keeps_flat_and_two_colour_blocks_and_is_deterministic():
    rng = np.random.default_rng(5)
    flat = np.repeat(np.repeat(rng.integers(0, 256, (16, 16, 3)), 4, 0), 4, 1).astype(np.float32)  # one colour a block
    decoded = decode_bc1(encode_bc1(flat), (64, 64))
    assert np.abs(decoded - flat).max() <= 2  # the nearest 565 colour alone is up to 4 codes off
    halves = np.zeros((4, 4, 3), np.float32)
    halves[:, 2:] = 255.0
    np.testing.assert_array_equal(decode_bc1(encode_bc1(halves), (4, 4)), halves)
    odd = rng.integers(0, 256, (7, 5, 3)).astype(np.float32)  # edges padded out to whole blocks
    blocks = encode_bc1(odd)
    assert len(blocks) == bc1_bytes((5, 7)) == 2 * 2 * 8 and decode_bc1(blocks, (5, 7)).shape == (7, 5, 3)
    np.testing.assert_array_equal(encode_bc1(odd), blocks)


def test_the_gpu_decodes_what_decode_bc1_says(gl_context):
    """texelFetch of a BC1 array against ``decode_bc1``: within 1.5 codes, the room GPUs take in rounding
    the thirds and in their sRGB decode (llvmpipe's largest: 1.1)."""
    image = np.random.default_rng(3).integers(0, 256, (16, 16, 3)).astype(np.float32)
    blocks = encode_bc1(image)
    objects = GLObjects()
    try:
        prog = objects.add(gl_context.program(vertex_shader=FULL_SCREEN, fragment_shader="""#version 330
uniform sampler2DArray u_array; out vec4 o;
void main() { o = texelFetch(u_array, ivec3(gl_FragCoord.xy, 0), 0); }"""))
        target = objects.add(gl_context.texture((16, 16), 4, dtype="f4"))
        fbo = objects.add(gl_context.framebuffer([target]))
        vao = objects.add(gl_context.vertex_array(prog, []))
        array = objects.add(BlockArray((16, 16), 1, [blocks.tobytes()]))
        prog["u_array"] = materials.TEXTURE_UNIT
        array.use(materials.TEXTURE_UNIT)
        fbo.use()
        vao.render(vertices=3)
        fetched = np.frombuffer(target.read(), np.float32).reshape(16, 16, 4)[..., :3]
    finally:
        objects.release()
    assert np.abs(linear_to_srgb(fetched) * 255.0 - decode_bc1(blocks, (16, 16))).max() <= 1.5


# -- which textures are BC1, their error and their bytes


@pytest.mark.parametrize("name", SHARED + list(GENERATED))
def test_each_texture_is_bc1_only_within_the_bound(name, gl_context):
    """Every level a BC1 texture keeps, read back from the driver and decoded, against the float64
    decode of the source (and its box-filtered levels): mean and p99 CIEDE2000 within the bound, every
    texel counted. A texture kept in RGBA16F is over it at level 0 or 1 by the same measure."""
    tex = source(name)
    h, w = tex.pixels.shape[:2]
    truth = box_levels(srgb_to_linear(tex.pixels[..., :3] / 255.0), 1 + int(np.log2(max(w, h))))
    with MaterialTextures(gl_context, [tex], {0}) as mats:
        storage = mats.storage[0]
        if storage == "bc1":
            array = mats.arrays["bc1"]
            assert array.size == (w, h) and array.levels >= min(2, len(truth))
            for level in range(array.levels):
                lw, lh = max(w >> level, 1), max(h >> level, 1)
                decoded = srgb_to_linear(decode_bc1(compressed_level(array, level), (lw, lh)) / 255.0)
                assert within_bound(colour_difference(truth[level], decoded)), (name, level)
        else:
            own = [colour_difference(level, srgb_to_linear(decode_bc1(encode_bc1(linear_to_srgb(level) * 255.0), level.shape[1::-1]) / 255.0))
                   for level in truth[:2]]
            assert not all(within_bound(e) for e in own), name
    if name in ("CesiumMan.glb", "Quaternius_Zombie_Basic.gltf", "Quaternius_Characters_Matt_SingleWeapon.gltf", "cells 16", "gradient", "ramp"):
        assert storage == "bc1", name  # what BC1 is for: real files, flat-coloured atlases, smooth gradients
    if name in ("noise", "cells 2", "four"):
        assert storage == "rgba16f", name  # more than two colours a block, everywhere


@pytest.mark.parametrize("name", ["CesiumMan.glb", "Quaternius_Zombie_Basic.gltf", "cells 8", "gradient"])
def test_a_bc1_texture_costs_at_most_2_bytes_a_texel(name, gl_context):
    """``gpu_bytes``: the BC1 levels' whole blocks and the coarse array's RGBA16F levels, against the
    texels of the full mip chain."""
    tex = source(name)
    h, w = tex.pixels.shape[:2]
    chain = [(max(w >> i, 1), max(h >> i, 1)) for i in range(1 + int(np.log2(max(w, h))))]
    with MaterialTextures(gl_context, [tex], {0}) as mats:
        assert mats.storage[0] == "bc1"
        fine = mats.arrays["bc1"].levels
        expected = sum(bc1_bytes(size) for size in chain[:fine])
        if "coarse" in mats.arrays:
            assert mats.coarse_lod == fine and mats.arrays["coarse"].size == (*chain[fine], 1)
            expected += sum(cw * ch for cw, ch in chain[fine:]) * 8
        assert mats.gpu_bytes() == expected
        assert mats.gpu_bytes() <= 2 * sum(cw * ch for cw, ch in chain)


def test_textures_over_the_bound_go_to_rgba16f_and_the_bc1_array_keeps_its_own_size(gl_context):
    """A 256-texel noise beside a 64-texel flat atlas: the noise fails, so the BC1 array is the atlas's
    size, not the noise's (the atlas is encoded again at 64 and measured again)."""
    small = Texture("cells", cells(64, 16), (REPEAT, REPEAT), LINEAR, MIPMAPPED)
    textures = [source("noise"), small]
    with MaterialTextures(gl_context, textures, {0, 1}) as mats:
        assert mats.storage == {0: "rgba16f", 1: "bc1"} and mats.layers == {0: 0, 1: 0}
        assert mats.arrays["bc1"].size == (64, 64) and mats.arrays["rgba16f"].size == (256, 256, 1)
        assert not within_bound(mats.errors[0][0]) and within_bound(mats.errors[1][0])
    with MaterialTextures(gl_context, textures, {0, 1}, compress=False) as mats:
        assert set(mats.storage.values()) == {"rgba16f"} and set(mats.arrays) == {"rgba16f"} and not mats.errors


def test_a_renderer_built_again_does_not_encode_again(gl_context, monkeypatch):
    tex = Texture("cells", cells(64, 16, seed=9), (REPEAT, REPEAT), LINEAR, MIPMAPPED)
    with MaterialTextures(gl_context, [tex], {0}) as first:
        blocks = compressed_level(first.arrays["bc1"], 0)

    def refused(*args):
        raise AssertionError("encoded again")

    monkeypatch.setattr(texture_layers, "encode_bc1", refused)
    copy = Texture("copy", tex.pixels.copy(), tex.wrap, tex.mag_filter, tex.min_filter)  # the same image, by content
    with MaterialTextures(gl_context, [copy], {0}) as again:
        np.testing.assert_array_equal(compressed_level(again.arrays["bc1"], 0), blocks)


# -- the driver without the format


def test_a_driver_without_s3tc_keeps_rgba16f_and_says_so_in_one_line(gl_context, monkeypatch):
    monkeypatch.setattr(materials, "S3TC_EXTENSION", "GL_EXT_not_this_driver")
    with MaterialTextures(gl_context, [source("cells 16")], {0}) as mats:
        assert mats.storage == {0: "rgba16f"} and set(mats.arrays) == {"rgba16f"}
        assert len(mats.notes) == 1 and "GL_EXT_not_this_driver" in mats.notes[0] and "\n" not in mats.notes[0]


def test_a_refused_format_leaves_no_texture_and_no_error(gl_context, monkeypatch):
    """A driver that lists S3TC but does not store the sRGB BC1 format (simulated with an enum that is
    no compressed format): RGBA16F, one line, no GL object left and no GL error queued."""
    from conftest import gl_census

    monkeypatch.setattr(materials, "COMPRESSED_SRGB_S3TC_DXT1", 0x1907)  # GL_RGB
    before = gl_census()
    with MaterialTextures(gl_context, [source("cells 16")], {0}) as mats:
        assert mats.storage == {0: "rgba16f"} and set(mats.arrays) == {"rgba16f"}
        assert len(mats.notes) == 1 and "refused" in mats.notes[0] and "\n" not in mats.notes[0]
        assert gl_context.error == "GL_NO_ERROR"
    assert gl_census() == before


def test_every_array_and_sampler_is_released(gl_context):
    from conftest import gl_census

    textures = [source("cells 8"), source("noise"), Texture("n", cells(256, 16, seed=4), (REPEAT, REPEAT), NEAREST, NEAREST)]
    before = gl_census()
    with MaterialTextures(gl_context, textures, {0, 1, 2}) as mats:
        assert set(mats.arrays) == {"bc1", "coarse", "rgba16f"}
        assert gl_census() != before
    assert gl_census() == before
    assert gl_context.error == "GL_NO_ERROR"


# -- sampling


def _bake_program(ctx):
    """skin.frag.glsl as the impostor bake compiles it (the albedo before lighting) behind a
    full-screen triangle whose coordinates span `u_scale` textures across the target."""
    vertex = """#version 330
uniform float u_scale;
uniform vec2 u_offset;
out vec3 v_world; out vec3 v_normal; out vec4 v_color; out vec2 v_uv; out float v_bake_depth;
void main() {
    vec2 p[3] = vec2[](vec2(-1, -1), vec2(3, -1), vec2(-1, 3));
    gl_Position = vec4(p[gl_VertexID], 0, 1);
    v_world = vec3(0); v_normal = vec3(0, 0, 1); v_color = vec4(1); v_bake_depth = 0.0;
    v_uv = u_offset + (p[gl_VertexID] * 0.5 + 0.5) * u_scale;
}"""
    return ctx.program(vertex_shader=vertex, fragment_shader=load_shader("skin.frag.glsl", {**FRAME_DEFINES, "TEXTURED": 1, "IMPOSTOR_BAKE": 1}))


def _sampled(ctx, mats, texture, scale, offset=(0.0, 0.0), side=64):
    """The linear albedo `texture` gives a side x side target at `scale` textures across it from `offset`."""
    objects = GLObjects()
    try:
        prog = objects.add(_bake_program(ctx))
        target = objects.add(ctx.texture((side, side), 4, dtype="f4"))
        fbo = objects.add(ctx.framebuffer([target]))
        vao = objects.add(ctx.vertex_array(prog, []))
        prog["u_albedo"] = materials.TEXTURE_UNIT
        prog["u_scale"] = scale
        prog["u_offset"] = offset
        mats.bind(texture, prog)
        fbo.use()
        vao.render(vertices=3)
        mats.unbind()
        return np.frombuffer(target.read(), np.float32).reshape(side, side, 4)[..., :3].astype(np.float64)
    finally:
        objects.release()


def test_filtering_on_the_bc1_path_mixes_light(gl_context):
    """Half way between a black and a white texel reads half the light (0.5), not half the sRGB codes
    (0.21), with the texture in BC1 as in RGBA16F."""
    halves = Texture("halves", _opaque(np.array([[[0, 0, 0], [255, 255, 255]]])), (REPEAT, REPEAT), LINEAR, LINEAR)
    for compress, storage in ((True, "bc1"), (False, "rgba16f")):
        with MaterialTextures(gl_context, [halves], {0}, compress=compress) as mats:
            assert mats.storage[0] == storage
            seen = _sampled(gl_context, mats, 0, scale=1e-4, offset=(0.5, 0.5))
        np.testing.assert_allclose(seen, 0.5, atol=2e-3)


def test_coarse_levels_take_over_where_bc1_would_be_over_the_bound(gl_context):
    """An atlas of 8-texel cells: BC1 holds its levels 0 and 1 exactly, and would be far off from level
    2 on (2-texel cells, four colours a block), so those come from the coarse array. Sampled at levels
    of detail 0 to 5, the hybrid reads what the all-RGBA16F array reads (across the blend, BC1's level
    1 against RGBA16F's); BC1's levels alone, clamped at level 1, read something else."""
    tex = source("cells 8")
    lods = (0.0, 0.5, 1.0, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0, 4.0, 5.0)
    with MaterialTextures(gl_context, [tex], {0}) as hybrid, MaterialTextures(gl_context, [tex], {0}, compress=False) as half:
        assert hybrid.coarse_lod == 2.0 and hybrid.arrays["bc1"].levels == 2
        off, alone = [], []
        for lod in lods:
            scale = 2.0 ** lod * 64 / 256  # textures across the 64-pixel target: lod texels a pixel, in log2
            reference = _sampled(gl_context, half, 0, scale)
            off.append(np.abs(_sampled(gl_context, hybrid, 0, scale) - reference).mean())
            coarse = hybrid.arrays.pop("coarse")
            try:
                alone.append(np.abs(_sampled(gl_context, hybrid, 0, scale) - reference).mean())
            finally:
                hybrid.arrays["coarse"] = coarse
    assert max(off) < max(alone) / 10, (off, alone)
    assert max(off[lods.index(2.0):]) < 1e-3  # from level 2 on, both read RGBA16F levels made alike (box filters)


def _textured_zombie(zombie, pixels: np.ndarray):
    """The zombie with `pixels` spread over each mesh by its front view (u from x, v from height)."""
    from test_textures import textured

    char = textured(zombie, pixels, (0.0, 0.0), mag=LINEAR, minify=MIPMAPPED)
    meshes = []
    for m in char.meshes:
        xy = m.positions[:, :2].astype(np.float64)
        uv = (xy - xy.min(axis=0)) / np.maximum(np.ptp(xy, axis=0), 1e-6)
        meshes.append(dataclasses.replace(m, uvs=uv.astype(np.float32)))
    return dataclasses.replace(char, meshes=meshes)


def test_the_41_path_draws_bc1_through_gl33_entry_points(tmp_path, zombie, gl_context, no_compute_features, monkeypatch):
    """The frame at 4.1 (macOS's path) with a textured crowd: BC1 made through GL 3.3 core entry points
    only, its bytes at most a quarter of RGBA16F's (2 bytes a texel), and its picture that of the RGBA16F path to a level
    or two of 255 (the crowd is drawn small, from the coarse levels)."""
    from test_textures import CROWD, SIZE

    from crowd import gl
    from crowd.asset.gltf_write import write_glb
    from crowd.pipeline_config import PipelineConfig
    from crowd.smoke import run_headless

    core_33 = {"glGenTextures", "glDeleteTextures", "glActiveTexture", "glBindTexture", "glBindBuffer", "glTexParameteri",
               "glCompressedTexImage3D", "glGetTexLevelParameteriv", "glGetError"}

    def loaded(name, prototype):
        assert name in core_33, f"{name} is not GL 3.3 core"
        return gl.current_context_function(name, prototype)

    monkeypatch.setattr(materials, "current_context_function", loaded)
    write_glb(_textured_zombie(zombie, cells(256, 16, seed=7)), tmp_path / "t.glb")
    runs = {}
    for storage in ("bc1", "rgba16f"):
        if storage == "rgba16f":
            monkeypatch.setattr(materials, "S3TC_EXTENSION", "GL_EXT_not_this_driver")
        runs[storage] = run_headless(PipelineConfig(**CROWD, model=tmp_path / "t.glb", gl="4.1"), 2, SIZE, ctx=gl_context)
        assert runs[storage]["gl_features"] == 410
    assert runs["bc1"]["gpu_bytes"]["textures"] * 4 <= runs["rgba16f"]["gpu_bytes"]["textures"]
    images = {k: v["_image"].astype(int) for k, v in runs.items()}
    diff = np.abs(images["bc1"] - images["rgba16f"]).max(axis=2)
    # (BC1 against the RGBA16F of the same texels: a few pixels where the packed coordinates of the merged
    # body and shirt land on a block edge differ by 3 levels)
    assert diff.max() <= 4 and np.count_nonzero(diff > 2) <= diff.size // 1000


def test_the_impostor_bake_draws_bc1_textures(zombie, gl_context, monkeypatch):
    """The impostor atlas's albedo of a textured character is the same with its texture in BC1 as in
    RGBA16F, to 3 levels of 255 (the cells are drawn small, mostly from the coarse array), and not that of the character drawn untextured."""
    from test_impostors import SMALL

    from crowd.anim.bake import bake
    from crowd.anim.roles import clips_used, match_roles
    from crowd.draw.impostor_bake import bake_atlas

    char = _textured_zombie(zombie, cells(256, 16, seed=8))
    roles, _ = match_roles(char.clips)
    baked = bake(char.skeleton, [char.clip(c) for c in clips_used(roles)[:1]])
    albedo = {}
    for storage in ("bc1", "rgba16f", "untextured"):
        if storage == "rgba16f":
            monkeypatch.setattr(materials, "S3TC_EXTENSION", "GL_EXT_not_this_driver")
        subject = char if storage != "untextured" else dataclasses.replace(
            char, meshes=[dataclasses.replace(m, texture=-1, uvs=None) for m in char.meshes], textures=[])
        albedo[storage] = bake_atlas(gl_context, subject, baked, SMALL).albedo.astype(int)
    assert np.abs(albedo["bc1"] - albedo["rgba16f"]).max() <= 3
    assert np.abs(albedo["bc1"] - albedo["untextured"]).max() > 24


@pytest.mark.parametrize("defines", [{}, {"SHADOWS": 1}, {"LOD_FADE": 1}, {"IMPOSTOR_BAKE": 1}])
def test_the_textured_fragment_shader_is_valid_glsl_330(defines, tmp_path):
    """skin.frag.glsl's textured variants through the Khronos reference compiler (stricter than Mesa
    about what #version 330 allows; .ci/run installs it, and the test skips without it)."""
    import shutil
    import subprocess

    validator = shutil.which("glslangValidator")
    if validator is None:
        pytest.skip("glslangValidator not installed (.ci/run installs glslang-tools)")
    path = tmp_path / "skin.frag"
    path.write_text(load_shader("skin.frag.glsl", {**FRAME_DEFINES, "TEXTURED": 1, **defines}))
    result = subprocess.run([validator, str(path)], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout
