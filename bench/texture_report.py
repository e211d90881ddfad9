"""crowd-bench textures: each base-colour texture as the renderer stores it (crowd.draw.materials),
against RGBA16F. Per texture: the storage chosen, each mip level's BC1 error against its linear layer
(CIEDE2000 mean and 99th percentile over every texel, and level 0's PSNR in sRGB codes), the GPU bytes
of both storages, and the encode time at load (the plan, its cache emptied). Beside them, at level 0,
two yardsticks: the two-channel colour plane (a per-texture plane through the colours, two unorm8
coordinates in linear light, 2 bytes a texel) and a JPEG at quality 95 of the same image.

With --agents, the textured draw's GPU time on both storages (the colour pass replayed and timed with
timer queries, as `crowd-bench frame` does), and where the driver reports it (NVIDIA's
GL_NVX_gpu_memory_info) the memory the driver gave each storage's arrays. RGBA16F is had as a driver
without EXT_texture_compression_s3tc has it (the extension hidden from the materials stage)."""

from __future__ import annotations

import contextlib
import io
import json
import time
from pathlib import Path

import numpy as np

from .common import device_cpu

SHARED_GLTF = Path(__file__).resolve().parents[2] / "shared" / "gltf"
MIPMAPPED = 9987  # LINEAR_MIPMAP_LINEAR
_AVAILABLE_VIDMEM_KB = 0x9049  # GL_NVX_gpu_memory_info's GPU_MEMORY_INFO_CURRENT_AVAILABLE_VIDMEM_NVX


def add_parsers(sub) -> None:
    p = sub.add_parser("textures", help="base-colour textures: BC1 against RGBA16F, CIEDE2000 per mip level, bytes, encode time; "
                                        "with --agents the textured draw's GPU ms on both")
    p.add_argument("--models", help="comma-separated .glb/.gltf files (default: those in shared/gltf beside the checkout)")
    p.add_argument("--large", type=int, default=2048, help="side of the texture (the first model's, resampled) whose load time is measured")
    p.add_argument("--agents", default="", help="comma-separated crowd sizes at which the first model's textured draw is timed")
    p.add_argument("--size", default="1920x1080", help="frame size WxH of the timed draw")
    p.add_argument("--frames", type=int, default=30, help="colour passes timed in a row, per storage and round")
    p.add_argument("--repeats", type=int, default=5, help="rounds, each storage timed once a round")
    p.add_argument("--json", type=Path, help="write the results as JSON to this file")
    p.set_defaults(run=run)


def synthetic() -> dict[str, np.ndarray]:
    """Harder images than the shared files: flat cells (an atlas) of 16, 8 and 2 texels, a smooth
    two-colour gradient, uniform noise, a red-to-green ramp and four hues side by side."""
    rng = np.random.default_rng(1)
    colours = rng.integers(0, 256, (64, 3))

    def cells(side, cell):
        return colours[(np.arange(side)[:, None] // cell * 7 + np.arange(side)[None, :] // cell * 3) % 64]

    x = np.linspace(0.0, 255.0, 256)
    ramp = np.zeros((1, 64, 3))
    ramp[0, :, 0], ramp[0, :, 1] = np.linspace(0, 255, 64), np.linspace(255, 0, 64)
    images = {"cells 16 (256)": cells(256, 16), "cells 8 (256)": cells(256, 8), "cells 2 (64)": cells(64, 2),
              "gradient (256)": np.stack(np.broadcast_arrays(x[None, :], x[:, None], np.full((256, 256), 128.0)), axis=-1).round(),
              "noise (256)": np.random.default_rng(2).integers(0, 256, (256, 256, 3)), "ramp (64x1)": ramp,
              "four hues (4x1)": np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 0]]])}
    return {k: np.concatenate([v.astype(np.uint8), np.full(v.shape[:2] + (1,), 255, np.uint8)], axis=2) for k, v in images.items()}


def textures(models: list[Path]):
    """(name, Texture) of each model's textures and of the synthetic images."""
    from crowd.asset.gltf import load_character
    from crowd.asset.model import LINEAR, REPEAT, Texture

    out = []
    for path in models:
        seen = set()
        for t in load_character(path).textures:
            if id(t.pixels) not in seen:
                seen.add(id(t.pixels))
                out.append((f"{path.name}: {t.name}", t))
    out += [(name, Texture(name, pixels, (REPEAT, REPEAT), LINEAR, MIPMAPPED)) for name, pixels in synthetic().items()]
    return out


def colour_plane(linear: np.ndarray) -> np.ndarray:
    """`linear` (H, W, 3) through the two-channel encoding: the plane through the texture's mean along its
    two principal axes, each coordinate as unorm8 over its range (linear in light, so it filters as
    light does). Returns the decoded linear colours."""
    pixels = linear.reshape(-1, 3)
    mean = pixels.mean(axis=0)
    axes = np.linalg.eigh(np.cov((pixels - mean).T) + np.eye(3) * 1e-12)[1][:, ::-1][:, :2]
    coords = (pixels - mean) @ axes
    low, high = coords.min(axis=0), coords.max(axis=0)
    span = np.maximum(high - low, 1e-12)
    stored = np.round((coords - low) / span * 255.0) / 255.0 * span + low
    return np.clip(mean + stored @ axes.T, 0.0, 1.0).reshape(linear.shape)


def jpeg_95(pixels: np.ndarray) -> np.ndarray:
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(pixels[..., :3])).save(out, format="JPEG", quality=95)
    return np.asarray(Image.open(out).convert("RGB"))


def texture_row(ctx, name: str, tex) -> dict:
    from crowd.draw import texture_layers
    from crowd.draw.materials import MaterialTextures
    from crowd.draw.texture_codec import colour_difference, encode_bc1, linear_to_srgb, srgb_to_linear
    from crowd.draw.texture_layers import bc1_error, linear_layer, linear_mip_levels

    h, w = tex.pixels.shape[:2]
    levels = linear_mip_levels(linear_layer(tex, (w, h))[..., :3].astype(np.float64))
    errors, psnr = [], None
    for i, level in enumerate(levels):
        codes = tex.pixels[..., :3].astype(np.float32) if i == 0 else linear_to_srgb(level).astype(np.float32) * 255.0
        blocks = encode_bc1(codes)
        errors.append([round(x, 3) for x in bc1_error(level, blocks, sample=None)])
        if i == 0:
            from crowd.draw.texture_codec import decode_bc1

            mse = float(np.mean((decode_bc1(blocks, (w, h)).astype(np.float64) - tex.pixels[..., :3]) ** 2))
            psnr = round(10 * np.log10(255.0 ** 2 / mse), 2) if mse > 0 else None
    truth = srgb_to_linear(tex.pixels[..., :3] / 255.0)
    plane = colour_difference(truth, colour_plane(truth))
    jpeg = colour_difference(truth, srgb_to_linear(jpeg_95(tex.pixels) / 255.0))
    texture_layers.forget_plans()  # the load as a first run has it
    t0 = time.perf_counter()
    with MaterialTextures(ctx, [tex], {0}) as mats:
        ctx.finish()
        load_s = time.perf_counter() - t0
        storage, fine, nbytes, notes = mats.storage[0], mats.arrays["bc1"].levels if "bc1" in mats.arrays else 0, mats.gpu_bytes(), mats.notes
    t0 = time.perf_counter()
    with MaterialTextures(ctx, [tex], {0}, compress=False) as half:
        ctx.finish()
        half_s = time.perf_counter() - t0
        half_bytes = half.gpu_bytes()
    texels = sum(lv.shape[0] * lv.shape[1] for lv in levels)
    return {"name": name, "size": [w, h], "storage": storage, "bc1_levels": fine, "levels": len(levels), "bc1_error": errors,
            "psnr_level0_db": psnr, "colour_plane_error": [round(x, 3) for x in plane], "jpeg95_error": [round(x, 3) for x in jpeg],
            "gpu_bytes": nbytes, "rgba16f_bytes": half_bytes, "bytes_per_texel": round(nbytes / texels, 3),
            "load_s": round(load_s, 3), "rgba16f_load_s": round(half_s, 3), "notes": notes}


def run(args) -> int:
    import moderngl
    from PIL import Image

    from crowd.asset.model import Texture
    from crowd.gl import describe, headless_context

    models = [Path(m) for m in args.models.split(",")] if args.models else sorted(
        p for p in SHARED_GLTF.glob("*") if p.suffix in (".glb", ".gltf")) if SHARED_GLTF.is_dir() else []
    ctx = headless_context()
    info = describe(ctx)
    device = f"{info['gl_renderer']}, {info['gl_version']}; {device_cpu()}; moderngl {moderngl.__version__}"
    print(device)
    print(f"{'texture':<52} {'size':>9} {'storage':>8} {'BC1 lv':>6} {'level 0 dE mean/p99':>20} {'worst kept p99':>14} "
          f"{'plane':>12} {'JPEG 95':>12} {'B/texel':>7} {'MB':>6} {'f16 MB':>6} {'load s':>6}")
    rows = []
    for name, tex in textures(models):
        row = texture_row(ctx, name, tex)
        rows.append(row)
        kept = max((e[1] for e in row["bc1_error"][:row["bc1_levels"]]), default=float("nan"))
        e0 = row["bc1_error"][0]
        print(f"{name[:52]:<52} {'x'.join(map(str, row['size'])):>9} {row['storage']:>8} {row['bc1_levels']:>3}/{row['levels']:<2} "
              f"{e0[0]:>9.2f} /{e0[1]:>7.2f} {kept:>14.2f} {row['colour_plane_error'][0]:>5.2f}/{row['colour_plane_error'][1]:<6.2f} "
              f"{row['jpeg95_error'][0]:>5.2f}/{row['jpeg95_error'][1]:<6.2f} {row['bytes_per_texel']:>7.3f} {row['gpu_bytes'] / 1e6:>6.3f} "
              f"{row['rgba16f_bytes'] / 1e6:>6.2f} {row['load_s']:>6.2f}")
    large = None
    if rows and models:
        first = next((t for n, t in textures(models[:1])), None)
        if first is not None:
            side = args.large
            pixels = np.asarray(Image.fromarray(first.pixels).resize((side, side), Image.Resampling.BICUBIC))
            big = Texture(f"{first.name} at {side}", pixels, first.wrap, first.mag_filter, first.min_filter)
            large = texture_row(ctx, big.name, big)
            print(f"load of one {side}x{side} texture: BC1 {large['load_s']:.2f} s (encode and measure every level), "
                  f"RGBA16F {large['rgba16f_load_s']:.2f} s; {large['gpu_bytes'] / 1e6:.2f} MB against {large['rgba16f_bytes'] / 1e6:.2f} MB")
    draws = draw_times(ctx, models[0], args) if args.agents and models else []
    if args.json:
        from crowd.files import atomic_write_bytes

        atomic_write_bytes(Path(args.json), json.dumps({"device": device, "error": "CIEDE2000 (mean, p99) per mip level, every texel",
                                                        "rows": rows, "large": large, "draws": draws}, indent=1).encode())
    ctx.release()
    return 0


def draw_times(ctx, model: Path, args) -> list[dict]:
    """The colour pass of a crowd of `model` on both storages, both pipelines built side by side and
    their passes timed in turns (`repeats` rounds of `frames` replays each, so that a busy host slows
    both alike), and the driver's memory for each where it reports it."""
    from crowd.gl import Offscreen
    from crowd.settings import parse

    size = parse("size", args.size)
    rows = []
    print(f"{model.name}: the colour pass, {size[0]}x{size[1]}, median of {args.repeats} x {args.frames} replays taken in turns")
    print(f"{'agents':>8} {'storage':>8} {'draw ms':>8} {'textures MB':>12} {'driver MB':>10}")
    with Offscreen(ctx, size) as target:
        for agents in [int(x) for x in args.agents.split(",")]:
            with contextlib.ExitStack() as stack:
                rows += _draw_times_of(ctx, model, agents, target, stack, args)
    return rows


def _draw_times_of(ctx, model: Path, agents: int, target, stack: contextlib.ExitStack, args) -> list[dict]:
    from unittest import mock

    from crowd.draw import materials
    from crowd.pipeline import CrowdPipeline, PipelineConfig
    from crowd.timing import PassTimer

    pipelines, driver, views = {}, {}, {}
    for storage in ("bc1", "rgba16f"):
        hidden = mock.patch.object(materials, "S3TC_EXTENSION", "GL_EXT_hidden") if storage == "rgba16f" else contextlib.nullcontext()
        with hidden:
            before = _available_kb(ctx)
            pipelines[storage] = pipeline = stack.enter_context(CrowdPipeline(ctx, PipelineConfig(agents=agents, model=model, weapons=False)))
            ctx.finish()
            driver[storage] = None if before is None else (before - _available_kb(ctx)) / 1e3
        pipeline.camera = pipeline.overview_camera(target.size[0] / target.size[1])
        for _ in range(3):
            pipeline.frame(target.framebuffer, 1 / 30)
        ctx.finish()
        views[storage] = pipeline.last.view
    samples = {storage: [] for storage in pipelines}
    with PassTimer(ctx) as timer:
        for repeat in range(args.repeats + 1):  # the first round brings the clocks up and is not counted
            for storage, pipeline in pipelines.items():
                for _ in range(args.frames):
                    with timer.gpu(storage):
                        pipeline.renderer.color_pass(target.framebuffer, views[storage], pipeline.processor)
                    timer.end_frame()
                timer.end_frame(drain=True)
                if repeat and storage in timer.samples:
                    samples[storage] += list(np.asarray(timer.samples[storage]))
                timer.samples.clear()
    rows = []
    for storage, pipeline in pipelines.items():
        stage = pipeline.renderer.materials
        row = {"agents": agents, "storage": storage, "chosen": sorted(set(stage.storage.values())),
               "draw_ms": round(float(np.median(samples[storage])), 3), "textures_mb": round(stage.gpu_bytes() / 1e6, 3),
               "driver_mb": driver[storage]}
        rows.append(row)
        print(f"{agents:>8} {storage:>8} {row['draw_ms']:>8.3f} {row['textures_mb']:>12.3f} "
              f"{'' if row['driver_mb'] is None else format(row['driver_mb'], '.1f'):>10}")
    return rows


def _available_kb(ctx) -> int | None:
    """The driver's free video memory in KB (NVIDIA's GL_NVX_gpu_memory_info), None where it has no such query."""
    import ctypes

    from crowd.gl import current_context_function

    if "GL_NVX_gpu_memory_info" not in ctx.extensions:
        return None
    value = ctypes.c_int(0)
    current_context_function("glGetIntegerv", ctypes.CFUNCTYPE(None, ctypes.c_uint, ctypes.POINTER(ctypes.c_int)))(_AVAILABLE_VIDMEM_KB, ctypes.byref(value))
    return value.value
