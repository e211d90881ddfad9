"""The one place that builds the GL stages of a crowd frame: processor, renderer, read-back, weapons.

``Stages.build(ctx, cast, spec)`` makes the stages a ``StageSpec`` asks for, for the characters of a
cast (``CastPart``: a character, its bake, its joint masks and legs), and nothing else: without armed
agents there is no read-back stage, no weapon meshes, and one palette instead of a ring. The pipeline, the benchmarks and the peers' crowd side all build through here, so the numbers
that tie one stage to another (the palette layout the renderer and read-back address, the history the
read-back latency needs) are derived once.

``Stages`` is a context manager: its GL objects are released when the block ends, however it ends, and
a build that fails half-way releases what it had made. Replacing one stage (``replace``) releases the
old one after the new one exists, so a failed rebuild keeps the working stage.
"""

from __future__ import annotations

from dataclasses import dataclass

import moderngl

from .anim.bake import AnimationBake
from .anim.processor import AnimationProcessor
from .anim.processor_inputs import resolve_path
from .asset.model import Character
from .draw.readback import SocketReadback
from .draw.render import CrowdRenderer, RenderError
from .draw.town import TownRenderer
from .draw.weapons import WeaponRenderer
from .gl import GL_LIMITS, feature_level, has_compute, limit_note
from .frame import MAX_LAYERS
from .settings import DEFAULTS


@dataclass(frozen=True)
class CastPart:
    """One character of a crowd, as the stages need it: what is drawn, what is played, the joint masks
    its upper-body actions use, and the legs the foot lock would hold."""

    character: Character
    bake: AnimationBake
    masks: object = None  # joint masks (masks, joints) or None
    legs: object = None  # crowd.anim.foot_lock.Legs, or None
    impostor: object = None  # crowd.draw.impostors.ImpostorAtlas where its far agents are drawn as impostors


def as_cast(cast) -> list[CastPart]:
    """A cast: a list of CastPart, or one (character, bake) pair for a crowd of one character."""
    if isinstance(cast, tuple) and len(cast) == 2 and isinstance(cast[0], Character):
        return [CastPart(*cast)]
    return list(cast)


@dataclass(frozen=True)
class StageSpec:
    """What the stages are built for; every field has the settings schema's default."""

    layers: int = MAX_LAYERS
    processor_path: str = DEFAULTS["processor"]
    interpolation: str = DEFAULTS["interpolation"]
    lod_distances: tuple = DEFAULTS["lod_distances"]
    shadows: bool = DEFAULTS["shadows"]
    culling: bool = DEFAULTS["culling"]
    occlusion: bool = DEFAULTS["occlusion"]
    cull: str = DEFAULTS["cull"]
    armed: bool = False  # somebody carries a weapon: the read-back stage and weapon meshes exist
    foot_lock: bool = DEFAULTS["foot_lock"]
    town: bool = False  # the built-in town is drawn (the town stage exists)
    readback_latency: int = DEFAULTS["readback_latency"]
    impostor_distance: float = DEFAULTS["impostor_distance"]  # metres, for the characters with an atlas
    lod_fade: float = DEFAULTS["lod_fade"]  # metres past each LOD switch over which the LODs cross-fade
    lod_error_px: float = DEFAULTS["lod_error_px"]  # pixels of error where a generated LOD starts
    gl_limit: int | None = GL_LIMITS[DEFAULTS["gl"]]  # the highest GL version whose features the stages use (None: the context's)

    @property
    def history(self) -> int:
        """Palettes the processor keeps: the read-back's frame and every frame after it, or just one."""
        return self.readback_latency + 1 if self.armed else 1


def build_processor(ctx: moderngl.Context, cast, spec: StageSpec, agents=0) -> AnimationProcessor:
    """`agents`: a count for a one-character cast, else one per character."""
    cast = as_cast(cast)
    path = resolve_path(ctx, spec.processor_path, spec.gl_limit)
    # The foot lock runs where it can: on the compute path, for characters with legs.
    legs = [part.legs if spec.foot_lock and path == "compute" else None for part in cast]
    processor = AnimationProcessor(ctx, [part.bake for part in cast], spec.layers, masks=[part.masks for part in cast], path=path,
                                   history=spec.history, interpolation=spec.interpolation, legs=legs,
                                   impostor_keys=[part.impostor is not None for part in cast])
    try:
        processor.resize(agents)
    except BaseException:
        processor.release()
        raise
    return processor


def build_renderer(ctx: moderngl.Context, cast, spec: StageSpec) -> CrowdRenderer:
    """The crowd's renderer; a character whose bake has morph tracks has its targets drawn (the processor
    writes its agents' pairs: the two must agree, and both follow the bake)."""
    cast = as_cast(cast)
    return CrowdRenderer(ctx, [part.character for part in cast], lod_distances=spec.lod_distances, shadows=spec.shadows,
                         culling=spec.culling, cull_path=cull_path(ctx, spec.cull, spec.gl_limit), weapons_visibility=spec.armed, occlusion=spec.occlusion,
                         morph_buffers=has_compute(ctx, spec.gl_limit),
                         town=spec.town, morphs=[part.bake.morphs is not None for part in cast],
                         impostors=[part.impostor for part in cast], impostor_distance=spec.impostor_distance, lod_fade=spec.lod_fade,
                         lod_error_px=spec.lod_error_px)


def cull_path(ctx: moderngl.Context, asked: str, limit: int | None = None) -> str:
    """"gpu", "feedback" or "cpu" for `asked` ("auto": gpu where the context runs compute shaders and `limit`,
    the "gl" setting's, lets the stages use them; else feedback where GL 4.0's indirect draws exist)."""
    compute = has_compute(ctx, limit)
    if asked == "gpu" and not compute:
        raise RenderError(f"the gpu cull path needs GL 4.3 compute shaders; this context is GL {ctx.version_code}{limit_note(ctx, limit)}")
    feedback = feature_level(ctx, limit) >= 400
    if asked == "feedback" and not feedback:
        raise RenderError(f"the feedback cull path needs GL 4.0 indirect draws; this context is GL {ctx.version_code}{limit_note(ctx, limit)}")
    return asked if asked != "auto" else ("gpu" if compute else "feedback" if feedback else "cpu")


def build_readback(ctx: moderngl.Context, processor: AnimationProcessor, spec: StageSpec) -> SocketReadback | None:
    return SocketReadback(ctx) if spec.armed else None


def build_town(ctx: moderngl.Context, spec: StageSpec) -> TownRenderer | None:
    from .asset.town import build_town as town

    return TownRenderer(ctx, town(), spec.shadows, gpu_cull=cull_path(ctx, spec.cull, spec.gl_limit) == "gpu") if spec.town else None


def build_weapons(ctx: moderngl.Context, cast, spec: StageSpec) -> WeaponRenderer | None:
    if not spec.armed:
        return None
    path = cull_path(ctx, spec.cull, spec.gl_limit)  # culled where the bodies are
    return WeaponRenderer(ctx, [part.character for part in as_cast(cast)], spec.shadows, gpu_cull=path == "gpu", feedback_cull=path == "feedback")


@dataclass
class Stages:
    processor: AnimationProcessor | None = None
    renderer: CrowdRenderer | None = None
    readback: SocketReadback | None = None
    weapons: WeaponRenderer | None = None
    town: TownRenderer | None = None

    ORDER = ("processor", "renderer", "readback", "weapons", "town")  # built in this order, released in reverse

    @classmethod
    def build(cls, ctx: moderngl.Context, cast, spec: StageSpec, agents=0) -> "Stages":
        """`cast`: a list of CastPart, or (character, bake) for one character; `agents`: a count for one
        character, else one per character."""
        stages = cls()
        try:
            stages.processor = build_processor(ctx, cast, spec, agents)
            stages.renderer = build_renderer(ctx, cast, spec)
            stages.readback = build_readback(ctx, stages.processor, spec)
            stages.weapons = build_weapons(ctx, cast, spec)
            stages.town = build_town(ctx, spec)
        except BaseException:
            stages.release()
            raise
        return stages

    def replace(self, name: str, stage) -> None:
        """Put a new stage (or None) in place of one, releasing the old one."""
        if name not in self.ORDER:
            raise KeyError(name)
        old = getattr(self, name)
        setattr(self, name, stage)
        if old is not None and old is not stage:
            old.release()

    def release(self) -> None:
        for name in reversed(self.ORDER):
            stage = getattr(self, name)
            if stage is not None:
                setattr(self, name, None)
                stage.release()

    def __enter__(self) -> "Stages":
        return self

    def __exit__(self, *exc) -> None:
        self.release()
