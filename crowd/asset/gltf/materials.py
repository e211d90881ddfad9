"""Materials as the file authored them (issue 18, point 2): the base colour factor, vertex colours and
the ``baseColorTexture``, sampled at its TEXCOORD set through its sampler's wrap and filter, with
KHR_texture_transform; KHR_materials_unlit draws the base colour without the sun, sky or shadows.

What the crowd's one lighting model cannot use (normal, metallic-roughness, occlusion and emissive
maps, alpha modes, specular-glossiness) is named in one warning. A KHR_materials_pbrSpecularGlossiness
material without pbrMetallicRoughness is drawn with its diffuse factor and texture as the base colour,
which is what it means. Props (the weapons the crowd holds) read their base colour only. The draw stage packs every image into one texture array,
so a textured piece is still one instanced draw per (piece, LOD).

Images are PNG or JPEG, embedded (a bufferView or a data URI) or a file in the model's folder, decoded
by Pillow (a dependency of moderngl-window already, so it adds nothing to install). An image that cannot
be used (missing, outside the folder, not PNG/JPEG, corrupt, larger than MAX_IMAGE_PIXELS, or past
MAX_TOTAL_PIXELS with the images before it) leaves its
meshes drawn with the base colour factor and vertex colours, and one warning naming the image and why:
the character itself is still right, and real exports often reference a texture nobody shipped.
Decoding is bounded before it starts: pixels per image and per file from the headers, and a JPEG's
count of scans (libjpeg decodes each over the whole image, so a file of thousands of tiny scans would
take minutes). 16-bit grey PNGs keep their values (Pillow's RGBA conversion clips them to white).
Texture coordinates that cannot be drawn (NaN, beyond ±MAX_UV) are refused, as positions are; a piece
whose coordinates span more than PACKED_UV_SPAN is named in a warning (it draws with float coordinates).
"""

from __future__ import annotations

import dataclasses
import io
import math
from dataclasses import dataclass

import numpy as np

from ...errors import CrowdError
from ..model import CLAMP_TO_EDGE, LINEAR, MIPMAP_FILTERS, NEAREST, PACKED_UV_SPAN, REPEAT, WRAPS, Texture

MAX_IMAGE_PIXELS = 4096 * 4096  # 64 MB as RGBA8: a character's atlas is at most 4k
MAX_TOTAL_PIXELS = 4 * MAX_IMAGE_PIXELS  # all images of one file together, decoded (256 MB)
MAX_TEXTURES = 256  # distinct images: the layers every GL 3.3 texture array may hold
MAX_JPEG_SCANS = 100  # progressive JPEGs have about 10; each scan is decoded over the whole image
MAX_UV = 1e4  # float32 keeps 1/1600 of a texel of a 1024 texture here; beyond, the texture is noise
_MAPS = ("normalTexture", "occlusionTexture", "emissiveTexture")
_SPEC_GLOSS = "KHR_materials_pbrSpecularGlossiness"  # archived, still exported: its diffuse is a base colour
_UNLIT = "KHR_materials_unlit"  # its base colour is drawn as it is, without the sun, sky or shadows
_FORMATS = {"PNG": "image/png", "JPEG": "image/jpeg"}


@dataclass(frozen=True)
class Surface:
    """What one primitive's material asks of the crowd's shading."""

    base_color: tuple[float, float, float, float]
    texture: int = -1  # index into Materials.textures
    texcoord: int = 0  # the TEXCOORD_n set the texture reads
    transform: np.ndarray | None = None  # (2, 3) KHR_texture_transform, or None
    unlit: bool = False  # KHR_materials_unlit: the base colour is the colour drawn (fog still falls on it)


def texture_transform(offset, rotation: float, scale) -> np.ndarray:
    """The (2, 3) matrix uv' = T(offset) R(rotation) S(scale) uv of KHR_texture_transform. The rotation
    turns the UVs counter-clockwise in the image as seen (v points down), which is
    u' = cos·u + sin·v, v' = -sin·u + cos·v: the extension's example (offset (0, 1), a quarter turn,
    scale 1/2) then maps the unit square onto the image's lower-left quadrant, as it says."""
    c, s = math.cos(rotation), math.sin(rotation)
    r = np.array([[c, s], [-s, c]]) @ np.diag(np.asarray(scale, np.float64))
    return np.concatenate([r, np.asarray(offset, np.float64)[:, None]], axis=1)


class Materials:
    """Reads materials, textures, samplers and images of one file through the importer's checked
    reader, each once; collects the character's ``textures`` and the warnings."""

    def __init__(self, reader):
        self.r = reader
        self.textures: list[Texture] = []
        self._by_texture: dict[int, int] = {}  # glTF texture index -> index in self.textures (-1: unusable)
        self._images: dict[int, np.ndarray | None] = {}
        self._left_out: set[str] = set()
        self._notes: list[str] = []
        self._pixels = 0  # decoded so far, against MAX_TOTAL_PIXELS
        self._layers: set[int] = set()  # distinct images in self.textures, against MAX_TEXTURES

    # -- per primitive

    def has_texture(self, prim: dict) -> bool:
        """Whether a primitive's material names a base-colour texture (read without decoding it)."""
        material = prim.get("material")
        mats = self.r.array("materials")
        if not isinstance(material, int) or not 0 <= material < len(mats) or not isinstance(mats[material], dict):
            return False
        pbr = mats[material].get("pbrMetallicRoughness")
        return isinstance(pbr, dict) and pbr.get("baseColorTexture") is not None

    def surface(self, prim: dict, label: str, textures: bool = True) -> Surface:
        """The primitive's base colour, texture and whether it is unlit; `textures=False` reads the colour
        only (props)."""
        surface = self._surface(prim, label, textures)
        material = prim.get("material")
        if surface.unlit or material is None:
            return surface
        extensions = self.r.obj(self.r.item("materials", material), "extensions", f"material {material}") or {}
        if _UNLIT in extensions:
            self.r.obj(extensions, _UNLIT, f"material {material} extensions")  # (an object, as glTF says)
            return dataclasses.replace(surface, unlit=True)
        return surface

    def _surface(self, prim: dict, label: str, textures: bool) -> Surface:
        r = self.r
        material = r.index(prim, "material", "materials", label)
        if material is None:
            return Surface((1.0, 1.0, 1.0, 1.0))
        where = f"material {material}"
        mat = r.item("materials", material)
        for key in _MAPS:
            if r.obj(mat, key, where) is not None:
                self._left_out.add(key)
        alpha = mat.get("alphaMode", "OPAQUE")
        if alpha != "OPAQUE":
            r.choice(mat, "alphaMode", where, ("OPAQUE", "MASK", "BLEND"))
            self._left_out.add(f"alphaMode {alpha}")
        pbr = r.obj(mat, "pbrMetallicRoughness", where)
        factor_key, texture_key = "baseColorFactor", "baseColorTexture"
        gloss = r.obj(r.obj(mat, "extensions", where) or {}, _SPEC_GLOSS, f"{where} extensions")
        if gloss is not None:
            self._left_out.add(f"{_SPEC_GLOSS} specular and glossiness")
            if pbr is None:  # what a viewer without the extension falls back to is white; its diffuse is meant
                pbr, factor_key, texture_key = gloss, "diffuseFactor", "diffuseTexture"
        if pbr is None:
            return Surface((1.0, 1.0, 1.0, 1.0))
        where = f"{where} {'pbrMetallicRoughness' if factor_key == 'baseColorFactor' else _SPEC_GLOSS}"
        base = tuple(float(x) for x in r.numbers(pbr, factor_key, 4, where, [1.0, 1.0, 1.0, 1.0]))
        if r.obj(pbr, "metallicRoughnessTexture", where) is not None:
            self._left_out.add("metallicRoughnessTexture")
        info = r.obj(pbr, texture_key, where)
        if info is None or not textures:
            return Surface(base)
        where = f"{where} {texture_key}"
        texture = self._texture(r.index(info, "index", "textures", where, required=True))
        texcoord = r.whole(info, "texCoord", where, default=0, hi=31)
        extensions = r.obj(info, "extensions", where) or {}
        transform = r.obj(extensions, "KHR_texture_transform", f"{where} extensions")
        matrix = None
        if transform is not None:
            twhere = f"{where} KHR_texture_transform"
            texcoord = r.whole(transform, "texCoord", twhere, default=texcoord, hi=31)
            rotation = transform.get("rotation", 0.0)
            if isinstance(rotation, bool) or not isinstance(rotation, (int, float)) or not math.isfinite(rotation) or abs(rotation) > MAX_UV:
                r.fail(f"{twhere}: rotation must be a finite number of radians, got {rotation!r:.40}")
            matrix = texture_transform(r.numbers(transform, "offset", 2, twhere, [0.0, 0.0]), float(rotation),
                                       r.numbers(transform, "scale", 2, twhere, [1.0, 1.0]))
            if np.any(np.abs(matrix) > MAX_UV):
                r.fail(f"{twhere} holds a value beyond ±{MAX_UV:g}")
        return Surface(base, texture, texcoord, matrix)

    def uvs(self, surface: Surface, raw: np.ndarray | None, label: str, what: str) -> np.ndarray | None:
        """The texture coordinates a textured surface samples at (transform applied), or None when the
        surface has no usable texture. `raw` is the TEXCOORD accessor's data (None: the primitive has none)."""
        if surface.texture < 0:
            return None
        if raw is None:
            self._notes.append(f"{label} has a base colour texture but no TEXCOORD_{surface.texcoord}; drawn without it")
            return None
        uv = np.asarray(raw, np.float64)
        if surface.transform is not None:
            uv = uv @ surface.transform[:, :2].T + surface.transform[:, 2]
        bad = ~np.isfinite(uv) | (np.abs(uv) > MAX_UV)
        if np.any(bad):
            self.r.fail(f"{what}: vertex {int(np.argmax(bad.any(axis=1)))} has a texture coordinate that is NaN or beyond ±{MAX_UV:g}")
        span = float(np.max(uv.max(axis=0) - uv.min(axis=0))) if len(uv) else 0.0
        if span > PACKED_UV_SPAN:
            self._notes.append(f"{label}: texture coordinates span {span:.4g}, more than the {PACKED_UV_SPAN:g} a packed vertex holds; "
                               "drawn with float coordinates, a third vertex attribute (slower)")
        return uv.astype(np.float32)

    def warnings(self) -> list[str]:
        out = list(dict.fromkeys(self._notes))
        if self._left_out:
            out.append(f"left out (the crowd's shading has no use for them): {', '.join(sorted(self._left_out))}")
        return out

    # -- textures, samplers, images

    def _texture(self, index: int) -> int:
        if index in self._by_texture:
            return self._by_texture[index]
        r = self.r
        where = f"texture {index}"
        tex = r.item("textures", index)
        source = r.index(tex, "source", "images", where)
        found = -1
        if source is None:
            others = sorted((r.obj(tex, "extensions", where) or {}).keys())
            self._notes.append(f"{where} has no PNG or JPEG source{' (only ' + ', '.join(others) + ')' if others else ''}; drawn without it")
        else:
            pixels = self._image(source)
            if pixels is not None and source not in self._layers:
                if len(self._layers) >= MAX_TEXTURES:
                    r.fail(f"{where}: more than {MAX_TEXTURES} base-colour images, the layers a texture array is sure to hold")
                self._layers.add(source)
            if pixels is not None:
                wrap, mag, minify = self._sampler(r.index(tex, "sampler", "samplers", where))
                name = r.item("images", source).get("name")
                found = len(self.textures)
                self.textures.append(Texture(name if isinstance(name, str) and name else f"image{source}", pixels, wrap, mag, minify))
        self._by_texture[index] = found
        return found

    def _sampler(self, index: int | None) -> tuple[tuple[int, int], int, int]:
        if index is None:
            return (REPEAT, REPEAT), LINEAR, 9987
        r = self.r
        where = f"sampler {index}"
        sampler = r.item("samplers", index)

        def enum(key, allowed, default):
            v = r.whole(sampler, key, where, default=default)
            if v not in allowed:
                r.fail(f"{where}: {key} must be one of {', '.join(map(str, allowed))}, got {v}")
            return v

        wrap = (enum("wrapS", WRAPS, REPEAT), enum("wrapT", WRAPS, REPEAT))
        return wrap, enum("magFilter", (NEAREST, LINEAR), LINEAR), enum("minFilter", (NEAREST, LINEAR, *MIPMAP_FILTERS), 9987)

    def _image(self, index: int) -> np.ndarray | None:
        if index in self._images:
            return self._images[index]
        r = self.r
        image = r.item("images", index)
        name = image.get("name")
        where = f"image {index}" + (f" ({name!r})" if isinstance(name, str) and name else "")
        try:
            pixels = decode_image(self._image_bytes(image, where), where, MAX_TOTAL_PIXELS - self._pixels)
            self._pixels += pixels.shape[0] * pixels.shape[1]
        except ValueError as exc:  # GltfImportError from the reader, or ImageError below: one line each
            self._notes.append(f"{str(exc).removeprefix(f'{r.where}: ')}; drawn without it")
            pixels = None
        self._images[index] = pixels
        return pixels

    def _image_bytes(self, image: dict, where: str) -> bytes:
        r = self.r
        uri = image.get("uri")
        view = r.index(image, "bufferView", "bufferViews", where)
        if view is not None and uri is not None:
            raise ImageError(f"{where} has both a uri and a bufferView (glTF allows one)")
        if view is not None:
            data, start, length, _ = r.view(view)
            return bytes(data[start:start + length])
        if uri is None:
            raise ImageError(f"{where} has neither a uri nor a bufferView")
        if not isinstance(uri, str):
            raise ImageError(f"{where}: uri must be a string")
        return r.uri_bytes(uri, where)  # a failure is a GltfImportError: _image makes it a warning


class ImageError(CrowdError, ValueError):
    """An image the crowd cannot use; the message is one line."""


def decode_image(data: bytes, where: str, budget: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """PNG or JPEG bytes → uint8 (H, W, 4) sRGB RGBA, refused in one line when it is anything else,
    corrupt, larger than MAX_IMAGE_PIXELS or than `budget` pixels (both checked from the header,
    before decoding)."""
    from PIL import Image  # imported here: only files with textures pay for it

    try:
        with Image.open(io.BytesIO(data), formats=tuple(_FORMATS)) as im:
            w, h = im.size
            if w * h > MAX_IMAGE_PIXELS:
                raise ImageError(f"{where} is {w}x{h}, more than the {MAX_IMAGE_PIXELS:,} pixels allowed")
            if w * h > budget:
                raise ImageError(f"{where} is {w}x{h}, past the {MAX_TOTAL_PIXELS:,} pixels all images of a file may decode to")
            # libjpeg decodes every scan over the whole image: thousands of tiny scans take minutes. In
            # entropy-coded data 0xFF is always followed by 0x00 or a restart marker, so this counts
            # start-of-scan markers (and those of an embedded thumbnail, which only errs on the safe side).
            scans = data.count(b"\xff\xda") if im.format == "JPEG" else 0
            if scans > MAX_JPEG_SCANS:
                raise ImageError(f"{where} is a JPEG of {scans} scans, more than the {MAX_JPEG_SCANS} allowed")
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):  # 16-bit grey: convert() would clip it to white
                im = Image.fromarray((np.asarray(im).astype(np.uint32) >> 8).clip(0, 255).astype(np.uint8))
            pixels = np.asarray(im.convert("RGBA"), dtype=np.uint8)
    except ImageError:
        raise
    except Exception as exc:  # Pillow's decoders raise a dozen types for corrupt data; each is one line here
        kind = "not a PNG or JPEG" if type(exc).__name__ == "UnidentifiedImageError" else f"cannot be decoded ({type(exc).__name__})"
        raise ImageError(f"{where} is {kind}") from None
    if pixels.ndim != 3 or pixels.shape[2] != 4 or 0 in pixels.shape:
        raise ImageError(f"{where} decodes to no pixels")
    return np.ascontiguousarray(pixels)


__all__ = ["CLAMP_TO_EDGE", "Materials", "Surface", "decode_image", "texture_transform", "MAX_UV", "MAX_IMAGE_PIXELS"]
