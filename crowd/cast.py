"""The cast of a running crowd: each character (``CastMember``) loaded, its roles matched, its clips baked
and its motion made on its own, and the impostor atlases of the characters whose far agents are drawn
as impostors.

A member is an identity, not a value: a cast may hold one model twice (nine zombies and nine brutes, or
two shares of one model with different roles), so nothing compares members or looks one up by its
fields; where a character's place in the cast matters (its morph variations' seed, its weapons'
numbers), the place is passed in.
"""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass, field

import moderngl
import numpy as np

from .anim.bake import AnimationBake, bake
from .anim.morph import MorphError, bake_morphs
from .anim.roles import clips_used, match_roles
from .asset.gltf import load_character
from .asset.lod import with_generated_lods
from .asset.model import Character, cast_weapons
from .pipeline_config import CharacterSpec, PipelineError
from .settings import SETTINGS
from .sim.motion import Motion, motion_for, upper_body_mask
from .sim.player import ROLES as SURVIVOR_ROLES
from .sim.player import SurvivorMotion, survivor_motion
from .stages import CastPart


@dataclass(eq=False)
class CastMember:
    """One character of the running crowd: its spec, what was loaded and baked for it, and its clips'
    playback speeds. It compares (and hashes) as itself, never field by field."""

    spec: CharacterSpec
    character: Character
    roles: dict
    role_notes: list
    bake: AnimationBake
    legs: object  # crowd.anim.foot_lock.Legs (possibly empty)
    masks: np.ndarray | None
    motion: Motion | None = None
    clip_speed: dict = field(default_factory=dict)  # clip name → playback speed (time scale), where not 1
    player: bool = False  # the survivor the player plays, not one of the crowd
    impostor: object = None  # its ImpostorAtlas (crowd.draw.impostors) where the scene draws its far agents as impostors

    def part(self) -> CastPart:
        return CastPart(self.character, self.bake, self.masks, self.legs, self.impostor)

    @property
    def name(self) -> str:
        return self.character.name


def load_cast(specs: tuple[CharacterSpec, ...], survivor: bool) -> list[CastMember]:
    """Each spec's character loaded and its roles matched (its notes named after it in a cast of
    several), then the survivor where the scene has one; nothing is baked yet."""
    cast = []
    for spec in specs:
        # A file without coarser LODs gets a chain of them (cached), for the crowd to draw from afar.
        character = with_generated_lods(load_character(spec.model, scale=SETTINGS["model_scale"].check(spec.model_scale, PipelineError),
                                                       libraries=spec.clips))
        roles, notes = match_roles(character.clips, spec.roles)
        if len(specs) > 1:
            notes = [f"{character.name}: {note}" for note in notes]
        masks = upper_body_mask(character.skeleton)
        cast.append(CastMember(spec, character, roles, notes, None, None, masks))
    if survivor:  # the player's character: the cast's last, one agent after the crowd's
        character = load_character("survivor")
        cast.append(CastMember(CharacterSpec("survivor", 0.0), character, {r: r for r in SURVIVOR_ROLES}, [], None, None,
                               upper_body_mask(character.skeleton), player=True))
    return cast


def bake_member(cast: list[CastMember], k: int, seed: int, fps, precision: str, bound_mm: float, morphs: bool,
                report=None) -> AnimationBake:
    """Character k's bake: the clips its roles play (only those), or the survivor's (crowd.sim.player.ROLES),
    with their morph weight tracks where `morphs` (the scene moves the character's targets), each agent's
    variation drawn from the scene's `seed` plus k; `report` is crowd.progress's callback."""
    member = cast[k]
    clips = SURVIVOR_ROLES if member.player else clips_used(member.roles)
    clips = [member.character.clip(c) for c in clips]
    joints = bake(member.character.skeleton, clips, fps, precision, bound_mm=bound_mm, report=report)
    if morphs:
        try:
            joints.morphs = bake_morphs(member.character, clips, joints, member.spec.morph, seed + k)
        except MorphError as exc:
            raise PipelineError(f"{member.character.name}: {exc}") from None
    return joints


def character_motion(cast: list[CastMember], k: int, clip_speed: dict | None = None) -> Motion:
    """Character k's Motion: its baked roles at its playback speeds (or `clip_speed`), its weapons
    numbered after those of the armed characters before it (as the weapon stage numbers them)."""
    member = cast[k]
    first = cast_weapons([m.character for m in cast])[0][k]
    motion = motion_for(member.character, member.bake, member.roles, member.clip_speed if clip_speed is None else clip_speed)
    return dataclasses.replace(motion, weapon_first=first)


def player_motion(member: CastMember) -> SurvivorMotion:
    """The survivor's controller: its baked clips at their playback speeds."""
    return survivor_motion(member.character, member.bake, 0 if member.masks is not None else -1, member.clip_speed)


def make_atlases(ctx: moderngl.Context, members: list[CastMember], bakes, want: bool, gl_limit) -> tuple[bool, list[str]]:
    """Each member's impostor atlas made for its bake in `bakes` (one per member), from the cache where it
    holds one, or dropped (`want` False). Returns whether anything changed (the processor and renderer
    must then be built again) and what making them said, a line each (a rebuilt cache), also printed."""
    from .draw.impostor_bake import load_atlas

    changed, notes = False, []
    for member, new_bake in zip(members, bakes):
        if not want:
            changed |= member.impostor is not None
            member.impostor = None
            continue
        if member.impostor is not None and member.impostor.bake is new_bake:
            continue
        atlas = load_atlas(ctx, member.character, new_bake, gl_limit=gl_limit)
        for note in atlas.notes:
            notes.append(f"{member.character.name}: {note}")
            print(f"{member.character.name}: {note}", file=sys.stderr)
        member.impostor = atlas
        changed = True
    return changed, notes
