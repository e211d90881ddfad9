"""Issue 18, point 2: materials as authored. Base colour factor, vertex colours and baseColorTexture
(its TEXCOORD set, its sampler's wrap and filter, KHR_texture_transform), PNG and JPEG images embedded
or beside the model, packed into one texture array so a piece stays one instanced draw per LOD."""

from __future__ import annotations

import base64
import dataclasses
import io
import json
import struct

import numpy as np
import pytest
from PIL import Image

from conftest import shared
from crowd.asset.gltf import load_character
from crowd.asset.gltf.reader import GltfImportError
from crowd.asset.gltf.materials import MAX_IMAGE_PIXELS, ImageError, decode_image, texture_transform
from crowd.asset.gltf_write import write_glb
from crowd.asset.model import CLAMP_TO_EDGE, LINEAR, MIRRORED_REPEAT, NEAREST, REPEAT, Texture
from crowd.draw.materials import MaterialTextures
from crowd.draw.texture_codec import srgb_to_linear
from crowd.draw.texture_layers import layer_size, linear_layer
from crowd.pipeline_config import PipelineConfig
from crowd.sim.config import AIConfig
from crowd.smoke import run_headless

SIZE = (320, 180)
CROWD = dict(agents=12, seed=4, shadows=False, weapons=False, ai=AIConfig(half_extent=3.0))
FOUR = np.array([[[255, 0, 0, 255], [0, 255, 0, 255], [0, 0, 255, 255], [255, 255, 0, 255]]], np.uint8)  # red green blue yellow


def png(pixels: np.ndarray, fmt="PNG", mode="RGBA") -> bytes:
    out = io.BytesIO()
    Image.fromarray(pixels, mode="RGBA").convert(mode).save(out, format=fmt)
    return out.getvalue()


def textured(character, pixels, uv, wrap=(REPEAT, REPEAT), mag=NEAREST, minify=NEAREST, base=(1.0, 1.0, 1.0, 1.0)):
    """`character` with one texture on every mesh, sampled at the constant coordinate `uv`."""
    tex = Texture("test", pixels, wrap, mag, minify)
    meshes = [dataclasses.replace(m, texture=0, base_color=base, uvs=np.tile(np.asarray(uv, np.float32), (len(m.positions), 1)))
              for m in character.meshes]
    return dataclasses.replace(character, meshes=meshes, textures=[tex], warnings=[])


def draw(path, ctx, **extra) -> np.ndarray:
    return run_headless(PipelineConfig(**CROWD, model=path, **extra), 2, SIZE, ctx=ctx)["_image"].astype(int)


# -- the maths


def test_texture_transform_follows_the_extensions_example():
    """offset (0, 1), a quarter turn and scale 1/2 use "only the lower left quadrant of the source image"."""
    m = texture_transform([0.0, 1.0], np.pi / 2, [0.5, 0.5])
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5]], np.float64)
    mapped = square @ m[:, :2].T + m[:, 2]
    np.testing.assert_allclose(mapped.min(0), [0.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(mapped.max(0), [0.5, 1.0], atol=1e-12)
    np.testing.assert_allclose(mapped[1], [0.0, 0.5], atol=1e-12)  # (1, 0) turns to the quadrant's top-left corner
    identity = texture_transform([0, 0], 0.0, [1, 1])
    np.testing.assert_array_equal(identity, [[1, 0, 0], [0, 1, 0]])


def test_srgb_decode_is_the_standard_curve():
    np.testing.assert_allclose(srgb_to_linear([0.0, 0.04045, 0.5, 1.0]), [0.0, 0.04045 / 12.92, 0.21404, 1.0], atol=2e-5)
    x = np.linspace(0, 1, 1001)
    assert np.all(np.diff(srgb_to_linear(x)) > 0)


def test_layers_are_resampled_in_linear_light_and_pixel_art_stays_square():
    checker = np.zeros((2, 2, 4), np.uint8)
    checker[0, 0] = checker[1, 1] = 255
    checker[..., 3] = 255
    smooth = linear_layer(Texture("c", checker, mag_filter=LINEAR), (1, 1))
    assert smooth[0, 0, 0] == pytest.approx(0.5, abs=0.02)  # the mean of the light, not of the sRGB codes (0.21)
    square = linear_layer(Texture("c", checker, mag_filter=NEAREST), (4, 4))
    assert set(np.unique(square[..., 0])) == {0.0, 1.0}
    assert layer_size([Texture("a", np.zeros((8, 64, 4), np.uint8)), Texture("b", np.zeros((32, 16, 4), np.uint8))]) == (64, 32)
    assert layer_size([Texture("a", np.zeros((1, 9000, 4), np.uint8))]) == (2048, 1)
    # 200 small images beside one 2048 square: halved until the array fits its budget (256 MB).
    many = [Texture("big", np.zeros((2048, 2048, 4), np.uint8))] + [Texture(f"s{i}", np.zeros((16, 16, 4), np.uint8)) for i in range(200)]
    w, h = layer_size(many)
    assert (w, h) == (256, 256) and 201 * w * h * 8 * 4 // 3 <= 256 << 20


# -- images


@pytest.mark.parametrize("mode", ["RGBA", "RGB", "L", "P", "LA"])
def test_png_images_of_every_mode_decode_to_rgba(mode):
    pixels = decode_image(png(FOUR, mode=mode), "image 0")
    expected = np.asarray(Image.fromarray(FOUR, "RGBA").convert(mode).convert("RGBA"))
    np.testing.assert_array_equal(pixels, expected)


def test_jpeg_images_decode():
    pixels = decode_image(png(np.repeat(np.repeat(FOUR, 16, 0), 16, 1), fmt="JPEG", mode="RGB"), "image 0")
    assert pixels.shape == (16, 64, 4) and np.all(pixels[..., 3] == 255)
    assert pixels[8, 8, 0] > 200 and pixels[8, 8, 1] < 60  # the red quarter is red


@pytest.mark.parametrize("data, needle", [
    (b"not an image at all", "is not a PNG or JPEG"),
    (b"GIF89a" + bytes(40), "is not a PNG or JPEG"),
    (b"", "is not a PNG or JPEG"),
])
def test_bad_image_bytes_are_one_line(data, needle):
    with pytest.raises(ImageError, match=needle) as info:
        decode_image(data, "image 3 ('skin')")
    assert "\n" not in str(info.value) and str(info.value).startswith("image 3 ('skin')")


def test_a_cut_png_and_a_gif_are_one_line():
    with pytest.raises(ImageError, match="cannot be decoded|is not a PNG"):
        decode_image(png(np.repeat(FOUR, 64, 0))[:60], "image 0")
    gif = io.BytesIO()
    Image.fromarray(FOUR, "RGBA").convert("P").save(gif, format="GIF")
    with pytest.raises(ImageError, match="is not a PNG or JPEG"):
        decode_image(gif.getvalue(), "image 0")


def test_images_past_the_files_pixel_budget_are_left_out(tmp_path, textured_doc, monkeypatch):
    from crowd.asset.gltf import materials

    doc, blob = textured_doc
    monkeypatch.setattr(materials, "MAX_TOTAL_PIXELS", 3)  # the 4-pixel strip is past it
    c = load_character(_as_gltf(tmp_path, doc, blob))
    assert not c.textures and any("past the 3 pixels all images of a file" in w for w in c.warnings)


def test_more_textures_than_an_array_holds_are_refused(tmp_path, textured_doc, monkeypatch):
    from crowd.asset.gltf import materials

    doc, blob = textured_doc
    monkeypatch.setattr(materials, "MAX_TEXTURES", 0)
    with pytest.raises(GltfImportError, match="more than 0 base-colour images"):
        load_character(_as_gltf(tmp_path, doc, blob))


def test_an_image_too_large_is_refused_from_its_header():
    side = int(np.sqrt(MAX_IMAGE_PIXELS)) + 1
    out = io.BytesIO()
    Image.new("1", (side, side)).save(out, format="PNG")  # 1 bit per pixel: a few kB on disk
    with pytest.raises(ImageError, match=f"{side}x{side}, more than"):
        decode_image(out.getvalue(), "image 0")


# -- the importer


def test_a_textured_character_comes_back_as_written(tmp_path, zombie):
    pixels = np.repeat(np.repeat(FOUR, 4, 0), 4, 1)
    char = textured(zombie, pixels, (0.3, 0.6), wrap=(MIRRORED_REPEAT, CLAMP_TO_EDGE), mag=LINEAR, minify=9985, base=(0.5, 1.0, 1.0, 1.0))
    write_glb(char, tmp_path / "t.glb")
    back = load_character(tmp_path / "t.glb")
    assert len(back.textures) == 1
    tex = back.textures[0]
    np.testing.assert_array_equal(tex.pixels, pixels)
    assert (tex.wrap, tex.mag_filter, tex.min_filter) == ((MIRRORED_REPEAT, CLAMP_TO_EDGE), LINEAR, 9985)
    for m in back.meshes:
        assert m.texture == 0 and m.base_color == (0.5, 1.0, 1.0, 1.0)
        np.testing.assert_array_equal(m.uvs, np.tile(np.float32([0.3, 0.6]), (len(m.positions), 1)))
    assert not any("texture" in w for w in back.warnings)


def _gltf_parts(path):
    data = path.read_bytes()
    n = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + n]), data[20 + n + 8:]


def _as_gltf(folder, doc, blob, name="t.gltf"):
    doc = json.loads(json.dumps(doc))
    doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
    path = folder / name
    path.write_text(json.dumps(doc))
    return path


@pytest.fixture
def textured_doc(tmp_path, zombie):
    write_glb(textured(zombie, FOUR, (0.25, 0.5)), tmp_path / "t.glb")
    return _gltf_parts(tmp_path / "t.glb")


def test_khr_texture_transform_is_applied_to_the_coordinates(tmp_path, textured_doc):
    doc, blob = textured_doc
    for mat in doc["materials"]:
        info = mat["pbrMetallicRoughness"].get("baseColorTexture")
        if info:
            info["extensions"] = {"KHR_texture_transform": {"offset": [0.0, 1.0], "rotation": np.pi / 2, "scale": [0.5, 0.5]}}
    c = load_character(_as_gltf(tmp_path, doc, blob))
    expected = np.array([0.25, 0.5]) @ texture_transform([0, 1], np.pi / 2, [0.5, 0.5])[:, :2].T + [0, 1]
    np.testing.assert_allclose(c.meshes[0].uvs[0], expected, atol=1e-6)


def test_external_images_beside_the_model_load_and_others_warn(tmp_path, textured_doc):
    doc, blob = textured_doc
    doc["images"][0].pop("bufferView")
    doc["images"][0].pop("mimeType")
    (tmp_path / "tex").mkdir()
    (tmp_path / "tex" / "skin.png").write_bytes(png(FOUR))
    for uri, loaded, needle in (("tex/skin.png", True, None), ("tex/missing.png", False, "is missing from the model's folder"),
                                ("../outside.png", False, "outside the file's folder"), ("tex", False, "not a regular file")):
        doc["images"][0]["uri"] = uri
        c = load_character(_as_gltf(tmp_path, doc, blob))
        assert (len(c.textures) == 1) == loaded, uri
        if loaded:
            np.testing.assert_array_equal(c.textures[0].pixels, FOUR)
        else:
            lines = [w for w in c.warnings if "image 0" in w]
            assert len(lines) == 1 and needle in lines[0] and "drawn without it" in lines[0], c.warnings
            assert all(m.texture == -1 for m in c.meshes)


def test_a_broken_image_warns_and_the_character_is_drawn_without_it(tmp_path, textured_doc):
    doc, blob = textured_doc
    doc["images"][0].pop("bufferView")
    doc["images"][0]["uri"] = "data:image/png;base64," + base64.b64encode(b"\x89PNG garbage").decode()
    c = load_character(_as_gltf(tmp_path, doc, blob))
    assert not c.textures and any("image 0" in w and "drawn without it" in w for w in c.warnings)


def test_maps_the_shading_cannot_use_are_named_in_one_warning(tmp_path, textured_doc):
    doc, blob = textured_doc
    mat = next(m for m in doc["materials"] if "baseColorTexture" in m["pbrMetallicRoughness"])
    mat["normalTexture"] = {"index": 0}
    mat["emissiveTexture"] = {"index": 0}
    mat["pbrMetallicRoughness"]["metallicRoughnessTexture"] = {"index": 0}
    mat["alphaMode"] = "MASK"
    c = load_character(_as_gltf(tmp_path, doc, blob))
    lines = [w for w in c.warnings if "left out" in w and "shading" in w]
    assert len(lines) == 1
    for name in ("normalTexture", "emissiveTexture", "metallicRoughnessTexture", "alphaMode MASK"):
        assert name in lines[0]
    assert len(c.textures) == 1  # the base colour is still drawn


def test_a_texture_without_coordinates_warns(tmp_path, textured_doc):
    doc, blob = textured_doc
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            prim["attributes"].pop("TEXCOORD_0", None)
    c = load_character(_as_gltf(tmp_path, doc, blob))
    assert any("no TEXCOORD_0" in w for w in c.warnings) and all(m.texture == -1 for m in c.meshes)


@pytest.mark.parametrize("mutate, needle", [
    (lambda d: d["samplers"][0].update(wrapS=1234), "sampler 0: wrapS must be one of"),
    (lambda d: d["samplers"][0].update(magFilter=9987), "sampler 0: magFilter must be one of"),
    (lambda d: d["textures"][0].update(source=7), "texture 0: source 7 is out of range"),
    (lambda d: d["materials"][-1]["pbrMetallicRoughness"]["baseColorTexture"].update(index=-1), "baseColorTexture: index -1 is out of range"),
    (lambda d: d["materials"][-1]["pbrMetallicRoughness"]["baseColorTexture"].update(
        extensions={"KHR_texture_transform": {"rotation": float("nan")}}), "rotation must be a finite number"),
    (lambda d: d["materials"][-1]["pbrMetallicRoughness"]["baseColorTexture"].update(
        extensions={"KHR_texture_transform": {"scale": [1e30, 1]}}), "beyond"),
])
def test_bad_texture_references_are_one_line(tmp_path, textured_doc, mutate, needle):
    doc, blob = textured_doc
    mutate(doc)
    with pytest.raises(GltfImportError, match=needle) as info:
        load_character(_as_gltf(tmp_path, doc, blob))
    assert "\n" not in str(info.value) and str(info.value).startswith("t.gltf: ")


def test_nan_texture_coordinates_are_refused(tmp_path, zombie):
    char = textured(zombie, FOUR, (0.25, 0.5))
    write_glb(char, tmp_path / "t.glb")
    doc, blob = _gltf_parts(tmp_path / "t.glb")
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"]]
    view = doc["bufferViews"][acc["bufferView"]]
    blob = bytearray(blob)
    blob[view["byteOffset"] + 8: view["byteOffset"] + 12] = struct.pack("<f", float("nan"))
    with pytest.raises(GltfImportError, match="TEXCOORD_0.*vertex 1 has a texture coordinate that is NaN"):
        load_character(_as_gltf(tmp_path, doc, bytes(blob)))


# -- on the GPU


def test_wrap_modes_sample_the_texel_the_sampler_names(tmp_path, zombie, gl_context):
    """A 4-texel strip sampled NEAREST at u = 1.4: REPEAT reads texel 1 (as u = 0.4 does), MIRRORED_REPEAT
    texel 2 (as 0.6), CLAMP_TO_EDGE texel 3 (as 0.9). Each picture equals its twin's pixel for pixel, and
    the three differ."""
    pictures = {}
    for name, uv, wrap in (("repeat", 1.4, REPEAT), ("repeat twin", 0.4, REPEAT), ("mirror", 1.4, MIRRORED_REPEAT),
                           ("mirror twin", 0.6, REPEAT), ("clamp", 1.4, CLAMP_TO_EDGE), ("clamp twin", 0.9, REPEAT)):
        path = tmp_path / f"{name.replace(' ', '_')}.glb"
        write_glb(textured(zombie, FOUR, (uv, 0.5), wrap=(wrap, REPEAT)), path)
        pictures[name] = draw(path, gl_context)
    for name in ("repeat", "mirror", "clamp"):
        np.testing.assert_array_equal(pictures[name], pictures[f"{name} twin"], err_msg=name)
    assert not np.array_equal(pictures["repeat"], pictures["mirror"])
    assert not np.array_equal(pictures["mirror"], pictures["clamp"])
    assert not np.array_equal(pictures["repeat"], pictures["clamp"])


def test_v_0_is_the_images_top_row(tmp_path, zombie, gl_context):
    """glTF puts v = 0 at the image's first (top) row: a column red over blue reads red at v = 0.1."""
    column = np.array([[[255, 0, 0, 255]], [[255, 0, 0, 255]], [[0, 0, 255, 255]], [[0, 0, 255, 255]]], np.uint8)
    pictures = {}
    for name, pixels, v in (("top", column, 0.1), ("red", column[:1], 0.5), ("blue", column[2:3], 0.5)):
        write_glb(textured(zombie, pixels, (0.5, v)), tmp_path / f"{name}.glb")
        pictures[name] = draw(tmp_path / f"{name}.glb", gl_context)
    np.testing.assert_array_equal(pictures["top"], pictures["red"])
    assert not np.array_equal(pictures["top"], pictures["blue"])


def test_linear_filtering_mixes_light_not_srgb_codes(tmp_path, zombie, gl_context):
    """Half way between a black and a white texel reads the grey of half the light (sRGB 188), not
    sRGB 128, the grey a filter over the stored codes would give."""
    halves = np.array([[[0, 0, 0, 255], [255, 255, 255, 255]]], np.uint8)
    pictures = {}
    for name, pixels in (("filtered", halves), ("half light", np.full((1, 1, 4), [188, 188, 188, 255], np.uint8)),
                         ("half codes", np.full((1, 1, 4), [128, 128, 128, 255], np.uint8))):
        path = tmp_path / f"{name.replace(' ', '_')}.glb"
        write_glb(textured(zombie, pixels, (0.5, 0.5), mag=LINEAR, minify=LINEAR), path)
        pictures[name] = draw(path, gl_context)
    to_light = np.abs(pictures["filtered"] - pictures["half light"]).max()
    to_codes = np.abs(pictures["filtered"] - pictures["half codes"]).max()
    assert to_light <= 3 < to_codes


def test_shared_texture_arrays_for_all_pieces_and_none_for_an_untextured_crowd(tmp_path, zombie, gl_context):
    base = run_headless(PipelineConfig(**CROWD), 2, SIZE, ctx=gl_context)
    assert "textures" not in base["gpu_bytes"]
    two = np.zeros((16, 8, 4), np.uint8)
    char = textured(zombie, FOUR, (0.1, 0.5))
    other = Texture("other", two, (REPEAT, REPEAT), LINEAR, 9987)
    meshes = [dataclasses.replace(m, texture=i % 2) for i, m in enumerate(char.meshes)]
    char = dataclasses.replace(char, meshes=meshes, textures=[char.textures[0], other])
    with MaterialTextures(gl_context, char.textures, {0, 1}, compress=False) as mats:
        assert mats.arrays["rgba16f"].size == (8, 16, 2) and mats.layers == {0: 0, 1: 1} and mats.mipmapped["rgba16f"]
        full = 8 * 16 + 4 * 8 + 2 * 4 + 1 * 2 + 1 * 1
        assert mats.gpu_bytes() == full * 2 * 4 * 2  # texels of the chain x layers x RGBA x f16
    with MaterialTextures(gl_context, char.textures, {0, 1}) as mats:  # the strip, scaled NEAREST to 8x16: two hues a block
        assert mats.storage == {0: "bc1", 1: "bc1"} and mats.layers == {0: 0, 1: 1} and mats.arrays["bc1"].size == (8, 16)
    write_glb(char, tmp_path / "two.glb")
    stats = run_headless(PipelineConfig(**CROWD, model=tmp_path / "two.glb"), 2, SIZE, ctx=gl_context)
    assert stats["last_frame"]["draws"] == base["last_frame"]["draws"]  # one instanced draw per (piece, LOD), textured or not
    assert stats["gpu_bytes"]["textures"] > 0


def test_a_textured_renderer_releases_its_array_and_samplers(tmp_path, zombie, gl_context):
    from test_architecture import gl_census

    from crowd.pipeline import CrowdPipeline

    write_glb(textured(zombie, FOUR, (0.1, 0.5)), tmp_path / "t.glb")
    before = gl_census()
    with CrowdPipeline(gl_context, PipelineConfig(**CROWD, model=tmp_path / "t.glb")) as pipeline:
        assert pipeline.stages.renderer.materials is not None
        assert gl_census() != before
    assert gl_census() == before


# -- real files


@pytest.mark.parametrize("name", ["CesiumMan.glb", "Quaternius_Zombie_Basic.gltf", "Quaternius_CubeWorld_Hedgehog.gltf",
                                  "Quaternius_Characters_Matt_SingleWeapon.gltf"])
def test_shared_textured_characters_draw_their_texture(name, tmp_path, gl_context):
    path = shared(name)
    c = load_character(path)
    assert len(c.textures) == 1 and all(m.texture == 0 for m in c.meshes)
    assert not any("textures left out" in w for w in c.warnings)
    image = draw(path, gl_context)
    # The same character drawn white: the texture changes the picture where the character stands.
    plain = dataclasses.replace(c, meshes=[dataclasses.replace(m, texture=-1, uvs=None) for m in c.meshes], textures=[])
    write_glb(plain, tmp_path / "plain.glb")
    flat = draw(tmp_path / "plain.glb", gl_context, model_scale=1.0)
    covered = np.abs(image - flat).max(axis=2) > 24
    assert covered.mean() > 0.002, name


def test_texture_coordinates_are_packed_within_a_60th_of_a_texel():
    from crowd.draw.packing import pack_vertices, unpack_uvs, uv_box

    rng = np.random.default_rng(3)
    for low, high in ((0.0, 1.0), (-3.0, 7.0), (0.25, 0.25)):
        uvs = rng.uniform(low, high, (500, 2)).astype(np.float32)
        uvs[0] = low
        mesh = dataclasses.replace(_one_mesh(), texture=0, uvs=uvs)
        packed = pack_vertices(mesh)
        corner, size = uv_box(uvs)
        back = unpack_uvs(packed["position_uv"][:, 3], corner, size)
        assert np.max(np.abs(back - uvs)) <= np.max(size) / 65535 / 2 + 1e-7
        np.testing.assert_array_equal(packed["position_uv"][:, :3].view(np.float32), mesh.positions)


def _one_mesh(n=500):
    from crowd.asset.model import SkinnedMesh

    rng = np.random.default_rng(0)
    joints = np.zeros((n, 4), np.uint16)
    weights = np.tile(np.float32([1, 0, 0, 0]), (n, 1))
    normals = np.tile(np.float32([0, 1, 0]), (n, 1))
    return SkinnedMesh("m", "body", 0, rng.normal(size=(n, 3)).astype(np.float32), normals, joints, weights, np.arange(n - n % 3, dtype=np.uint32))


def test_mirrored_repeat_filters_an_edge_texel_with_itself(tmp_path, zombie, gl_context):
    """At a fold (u = 1, and u = 0) linear filtering under MIRRORED_REPEAT reads the edge texel alone,
    as GL's mirrored repeat does; a repeating sampler under the fold would mix in the opposite edge."""
    pictures = {}
    for name, pixels, uv, wrap in (("fold at 1", FOUR, 1.0, MIRRORED_REPEAT), ("yellow", FOUR[:, 3:4], 0.5, REPEAT),
                                   ("fold at 0", FOUR, 0.0, MIRRORED_REPEAT), ("red", FOUR[:, 0:1], 0.5, REPEAT)):
        path = tmp_path / f"{name.replace(' ', '_')}.glb"
        write_glb(textured(zombie, np.ascontiguousarray(pixels), (uv, 0.5), wrap=(wrap, REPEAT), mag=LINEAR, minify=LINEAR), path)
        pictures[name] = draw(path, gl_context)
    assert np.abs(pictures["fold at 1"] - pictures["yellow"]).max() <= 1
    assert np.abs(pictures["fold at 0"] - pictures["red"]).max() <= 1


def _gradient_character(zombie, offset=0.0):
    """The zombie with a smooth 64-texel gradient along u, u running with each vertex's height."""
    ramp = np.zeros((1, 64, 4), np.uint8)
    ramp[0, :, 0] = np.linspace(0, 255, 64)
    ramp[0, :, 1] = np.linspace(255, 0, 64)
    ramp[0, :, 3] = 255
    char = textured(zombie, ramp, (0.0, 0.5), mag=LINEAR, minify=LINEAR)
    meshes = []
    for m in char.meshes:
        u = (m.positions[:, 1] - m.positions[:, 1].min()) / max(float(np.ptp(m.positions[:, 1])), 1e-6)
        meshes.append(dataclasses.replace(m, uvs=np.stack([u + offset, np.full_like(u, 0.5)], axis=1).astype(np.float32)))
    return dataclasses.replace(char, meshes=meshes)


def test_packed_coordinates_draw_as_float_ones_do(tmp_path, zombie, gl_context, monkeypatch):
    """Coordinates that vary over the body: the packed layout's decode in the shader draws what float
    coordinates draw, to 2 levels of 255; and a piece whose coordinates span more than PACKED_UV_SPAN
    (one stray vertex at u = 1000, which would make the packed step 1000/65535) is drawn with float
    coordinates and says so."""
    from crowd.draw import packing

    write_glb(_gradient_character(zombie), tmp_path / "g.glb")
    packed = draw(tmp_path / "g.glb", gl_context)
    with monkeypatch.context() as m:
        m.setattr(packing, "PACKED_UV_SPAN", -1.0)  # every textured piece takes the float layout
        wide = draw(tmp_path / "g.glb", gl_context)
    assert np.abs(packed - wide).max() <= 2
    far = _gradient_character(zombie)
    far = dataclasses.replace(far, meshes=[dataclasses.replace(m, uvs=np.where(np.arange(len(m.uvs))[:, None] == 0, m.uvs + [[1000.0, 0.0]], m.uvs).astype(np.float32))
                                           for m in far.meshes])
    write_glb(far, tmp_path / "far.glb")
    loaded = load_character(tmp_path / "far.glb")
    assert any("span" in w and "float coordinates" in w for w in loaded.warnings)
    assert all(packing.uv_layout(m) == "wide" for m in loaded.meshes)


def test_sixteen_bit_grey_pngs_keep_their_values():
    out = io.BytesIO()
    Image.fromarray(np.array([[1000, 32768, 65535]], np.uint16)).save(out, format="PNG")
    np.testing.assert_array_equal(decode_image(out.getvalue(), "image 0")[0, :, 0], [3, 128, 255])


def test_a_jpeg_of_thousands_of_scans_is_refused_before_decoding():
    data = png(np.repeat(np.repeat(FOUR, 8, 0), 8, 1), fmt="JPEG", mode="RGB")
    bomb = data[:-2] + b"\xff\xda" * 500 + data[-2:]
    with pytest.raises(ImageError, match="JPEG of 50[0-9] scans, more than the 100 allowed"):
        decode_image(bomb, "image 0")


def test_an_image_with_both_a_uri_and_a_buffer_view_is_left_out(tmp_path, textured_doc):
    doc, blob = textured_doc
    doc["images"][0]["uri"] = "skin.png"
    c = load_character(_as_gltf(tmp_path, doc, blob))
    assert not c.textures and any("both a uri and a bufferView" in w for w in c.warnings)


def test_specular_glossiness_diffuse_is_the_base_colour(tmp_path, textured_doc):
    doc, blob = textured_doc
    mat = next(m for m in doc["materials"] if "baseColorTexture" in m["pbrMetallicRoughness"])
    pbr = mat.pop("pbrMetallicRoughness")
    mat["extensions"] = {"KHR_materials_pbrSpecularGlossiness": {"diffuseFactor": [0.5, 0.25, 1.0, 1.0],
                                                                  "diffuseTexture": pbr["baseColorTexture"]}}
    c = load_character(_as_gltf(tmp_path, doc, blob))
    textured_meshes = [m for m in c.meshes if m.texture == 0]
    assert textured_meshes and textured_meshes[0].base_color == (0.5, 0.25, 1.0, 1.0)
    assert any("KHR_materials_pbrSpecularGlossiness specular and glossiness" in w for w in c.warnings)


def test_a_refused_read_counts_nothing_against_the_file_budget(tmp_path, textured_doc, monkeypatch):
    from crowd.asset.gltf import reader

    path = _as_gltf(tmp_path, *textured_doc)
    file = reader.Reader(path)
    before = file._loaded_bytes
    monkeypatch.setattr(reader, "MAX_FILE_BYTES", before + 10)
    with pytest.raises(GltfImportError, match="would bring the bytes read to"):
        file._charge_file(11, "image 0")
    assert file._loaded_bytes == before
    file._charge_file(10, "buffer 1")  # what comes after still fits
