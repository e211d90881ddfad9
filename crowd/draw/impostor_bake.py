"""The impostor atlas's bake and its cache (crowd.draw.impostors says what the atlas holds): the clips
rendered by the animation processor and the crowd's own skinned draw (CrowdRenderer.bake_pass), so an
impostor shows what the mesh would. Apart from crowd.draw.impostors because it draws through the renderer,
which itself draws the impostors."""

from __future__ import annotations

import copy
import math

import moderngl
import numpy as np

from ..anim.bake import AnimationBake
from ..anim.palette_reference import reference_palette
from ..anim.processor import AnimationProcessor
from ..anim.processor_inputs import resolve_path
from ..asset.model import Character
from ..frame import CLIP, MASK, PHASE, WEIGHT, Camera, Instances, empty_layers
from ..cache import cache_dir
from ..gl import GLObjects, has_compute
from .impostors import (ImpostorAtlas, ImpostorError, ImpostorSettings, atlas_key, clip_boxes, clip_frames, read_atlas,
                        save_atlas, skinned_points, view_axes)
from .render import CrowdRenderer


def bake_atlas(ctx: moderngl.Context, character: Character, bake: AnimationBake, settings: ImpostorSettings | None = None,
               gl_limit: int | None = None) -> ImpostorAtlas:
    """Render the atlas of `character` playing `bake`'s clips (see the module docstring), with the GL
    features `gl_limit` allows (crowd.gl.feature_level: the "gl" setting's)."""
    settings = (settings or ImpostorSettings()).validate()
    per_clip = clip_frames(bake, settings.rate)
    frames = sum(n for n, _, _ in per_clip)
    frame_clip = np.repeat(np.arange(len(per_clip)), [n for n, _, _ in per_clip])
    layers = empty_layers(frames, 1)
    layers[:, 0, CLIP] = frame_clip
    layers[:, 0, PHASE] = np.concatenate([p for _, p, _ in per_clip])
    layers[:, 0, WEIGHT] = 1.0
    layers[:, 0, MASK] = -1.0
    plain = copy.copy(bake)
    plain.morphs = None  # the pose only: morph targets are not baked
    points = skinned_points(character, reference_palette(plain, layers))
    boxes = clip_boxes(points, frame_clip, len(per_clip), settings)
    cw, ch = (int(x) for x in settings.cell)
    columns = settings.columns
    max_size = int(ctx.info["GL_MAX_TEXTURE_SIZE"])
    if columns * cw > max_size:
        raise ImpostorError(f"{columns} views of {cw} pixels are wider than this GPU's largest texture ({max_size})")
    # Layers of at most 8,192 texels (or the GPU's largest texture), filled evenly.
    layer_count = -(-frames // max(1, min(max_size, 8192) // ch))
    rows = -(-frames // layer_count)
    size = (columns * cw, rows * ch)
    albedo = np.zeros((layer_count, size[1], size[0], 4), np.uint8)
    normal_depth = np.zeros_like(albedo)
    objects = GLObjects()
    try:
        proc = objects.add(AnimationProcessor(ctx, plain, 1, path=resolve_path(ctx, "auto", gl_limit)))
        renderer = objects.add(CrowdRenderer(ctx, character, lod_distances=(1e9, 2e9, 3e9), shadows=False, culling=False, cull_path="cpu",
                                             morphs=[False], morph_buffers=has_compute(ctx, gl_limit)))
        proc.resize(frames)
        proc.process(layers)
        choices = {group: np.zeros(frames, np.int64) for group in renderer.group_names}
        instances = Instances(np.zeros((frames, 3)), np.zeros(frames, np.float32), np.ones(frames, np.float32),
                              np.full((frames, 4), 255, np.uint8), choices)
        renderer.prepare(Camera(eye=np.zeros(3), target=np.array([0.0, 0.0, -1.0])), instances, palette=proc.layout)
        per_frame = objects.add(ctx.texture((frames, 1), 4, boxes[frame_clip].astype(np.float32).tobytes(), dtype="f4"))
        targets = [objects.add(ctx.texture(size, 4)) for _ in range(2)]
        depth = objects.add(ctx.depth_renderbuffer(size))
        fbo = objects.add(ctx.framebuffer(color_attachments=targets, depth_attachment=depth))
        for layer in range(layer_count):
            fbo.use()
            fbo.viewport = (0, 0, *size)
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            for e, elevation in enumerate(settings.elevations):
                for v in range(settings.views):
                    right, up, toward = view_axes(2.0 * math.pi * v / settings.views, math.radians(elevation))
                    renderer.bake_pass(fbo, proc, per_frame, {"u_bake_right": right, "u_bake_up": up, "u_bake_toward": toward,
                                                              "u_bake_column": e * settings.views + v, "u_bake_columns": columns,
                                                              "u_bake_first": layer * rows, "u_bake_rows": rows})
            for target, out in zip(targets, (albedo, normal_depth)):
                out[layer] = np.frombuffer(target.read(), np.uint8).reshape(size[1], size[0], 4)
    finally:
        objects.release()
    first = np.concatenate([[0], np.cumsum([n for n, _, _ in per_clip])[:-1]])
    table = np.zeros((len(per_clip), 2, 4), np.float32)
    table[:, 0, 0] = first
    table[:, 0, 1] = [n for n, _, _ in per_clip]
    table[:, 0, 2] = [float(loop) for _, _, loop in per_clip]
    table[:, 1] = boxes
    return ImpostorAtlas(settings, tuple(c.name for c in bake.clips), table, albedo, normal_depth, rows).validate()



def load_atlas(ctx: moderngl.Context, character: Character, bake: AnimationBake, settings: ImpostorSettings | None = None,
               cache: bool = True, gl_limit: int | None = None) -> ImpostorAtlas:
    """The character's atlas from the cache, or baked (and cached; `gl_limit` as for ``bake_atlas``: the
    paths agree to float32's noise, so the cache does not tell them apart); a cache file that does not read or
    check is rebuilt, and the atlas's ``notes`` say so in one line."""
    settings = (settings or ImpostorSettings()).validate()
    notes = []
    path = cache_dir("impostors") / f"{character.name}-{atlas_key(character, bake, settings)}.npz" if cache else None
    if path is not None and path.exists():
        try:
            atlas = read_atlas(path)
            if atlas.settings == settings and atlas.clip_names == tuple(c.name for c in bake.clips):
                atlas.bake = bake
                return atlas
            notes.append(f"impostor cache {path} was made for other settings: rebuilt")
        except ImpostorError as exc:
            notes.append(f"impostor cache rebuilt: {exc}")
    atlas = bake_atlas(ctx, character, bake, settings, gl_limit)
    atlas.notes = notes
    atlas.bake = bake
    if path is not None:
        try:
            save_atlas(path, atlas)
        except OSError as exc:
            atlas.notes.append(f"impostor cache not written ({path}: {exc.strerror or exc})")
    return atlas
