"""What the AI knows of a character's baked clips (``Motion``): clip indices, durations, locomotion
strides and speeds, and where its feet pivot; strides and pivots measured from the clips' planted feet
where the file gives none."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..asset.model import CONTACT_M, foot_joints
from ..asset.pose import global_matrices, sample_clip
from ..asset.units import footprint_radius
from ..search import golden_section_max
from ..settings import SETTINGS
from .config import AIError

DEFAULT_WALK_SPEED = 1.0  # m/s, for imported walks without a stride (their feet will slide)
DEFAULT_RUN_SPEED = 3.0
RUN_OVER_WALK = 1.8  # top speed of a runner over a walker when one clip plays both
FOOT_SAMPLES = 64  # phases a locomotion clip's pivot is tabled at (Motion.pivots)
WALK_SLOWEST = 0.25  # the slowest a walk plays, as a share of its own rate (Motion.walk_slowest)


@dataclass(frozen=True)
class Motion:
    """What the AI needs to know of the baked clips: indices, durations and locomotion strides."""

    clip: dict  # role → clip index in the bake, or -1 when the role has no clip
    duration: dict  # role → seconds (0 for roles without a clip)
    walk_stride: float  # metres per cycle
    run_stride: float
    walk_speed: float  # m/s at which the clip's feet do not slide (for a factor-1 agent)
    run_speed: float
    upper_body_mask: int  # mask row for upper-body actions, or -1 (whole body)
    head_count: int = 0
    weapon_count: int = 0
    notes: tuple = ()
    # Share of the walk speed down to which the walk plays alone, slowed (locomotion_weights): where its
    # slowed rate is idle's own, so the phase's rate does not jump as idle fades in; within [1/4, 1].
    walk_slowest: float = 1.0
    # Where agents pivot when they turn (turn_about_planted_foot): per clip (idle, walk, run) and phase
    # (FOOT_SAMPLES + 1 evenly spaced, the last at phase 1), the model-space (x, z) of the middle of the
    # foot joints on the ground and 1 where one is (3, FOOT_SAMPLES + 1, 3); None: about their origin.
    pivots: np.ndarray | None = dataclasses.field(default=None, compare=False)
    weapon_first: int = 0  # its first weapon's number among the cast's (a crowd of several characters)
    # Metres from where it stands to the farthest point of its idle pose (crowd.asset.units.footprint_radius):
    # separation gives a character wider than a person room in proportion (crowd.sim.separation).
    footprint: float = 0.0

    @staticmethod
    def from_bake(bake, roles: dict, strides: dict, upper_body_mask: int = -1, head_count: int = 0, weapon_count: int = 0,
                  clip_speed: dict | None = None) -> "Motion":
        """`clip_speed` (clip name → time scale, default 1) plays a clip faster or slower: its duration is
        divided by the scale, so a walk played 1.5x faster also moves 1.5x faster and its feet stay put."""
        clip, duration, notes = {}, {}, []
        for role in ("idle", "walk", "run", "attack", "hit", "death"):
            name = roles.get(role)
            clip[role] = bake.clip_index(name) if name else -1
            speed = SETTINGS["clip_speed"].check((clip_speed or {}).get(name, 1.0), AIError, f"clip {name!r}") if name else 1.0
            duration[role] = max(bake.clips[clip[role]].duration / speed, 1e-3) if name else 0.0
        walk_stride = float(strides.get(roles["walk"]) or 0.0)
        if walk_stride <= 0:
            walk_stride = DEFAULT_WALK_SPEED * duration["walk"]
            notes.append(f"walk clip {roles['walk']!r} has no stride; it moves at {DEFAULT_WALK_SPEED} m/s and its feet may slide")
        walk_speed = walk_stride / duration["walk"]
        if roles["run"] == roles["walk"]:
            # One clip for both: running is the walk played faster (the stride stays, the rate goes up).
            run_stride, run_speed = walk_stride, walk_speed * RUN_OVER_WALK
        else:
            run_stride = float(strides.get(roles["run"]) or 0.0)
            if run_stride <= 0:
                run_stride = DEFAULT_RUN_SPEED * duration["run"]
                notes.append(f"run clip {roles['run']!r} has no stride; it moves at {DEFAULT_RUN_SPEED} m/s and its feet may slide")
            run_speed = max(run_stride / duration["run"], walk_speed * 1.01)
        slowest = duration["walk"] / duration["idle"] if duration["idle"] > 0 else WALK_SLOWEST
        return Motion(clip, duration, walk_stride, run_stride, walk_speed, run_speed, int(upper_body_mask), int(head_count),
                      int(weapon_count), tuple(notes), float(np.clip(slowest, WALK_SLOWEST, 1.0)))


def upper_body_mask(skeleton) -> np.ndarray | None:
    """(1, J) mask: 1 for the first joint named like a spine and everything below it, else 0.
    None when no joint is named like a spine (then actions play on the whole body)."""
    names = [n.lower() for n in skeleton.names]
    start = next((j for j, n in enumerate(names) if any(w in n for w in ("spine", "chest", "torso"))), None)
    if start is None:
        return None
    mask = np.zeros(skeleton.joint_count, np.float32)
    mask[start] = 1.0
    for j, p in enumerate(skeleton.parents):  # parents come first, so one pass suffices
        if p >= 0 and mask[p] > 0:
            mask[j] = 1.0
    return mask[None]


def motion_for(character, bake, roles: dict, clip_speed: dict | None = None) -> Motion:
    """The Motion of a character's baked roles. Upper-body actions use mask row 0 when the skeleton has
    an upper body (the processor gets `upper_body_mask(skeleton)` as its masks); heads are the pieces of
    the "head" variation group; weapons are the props the character can hold in a socket."""
    strides = {c.name: (c.stride or 0.0) for c in character.clips}
    measured = []
    for role in ("walk", "run"):
        name = roles.get(role)
        if name and strides.get(name, 0.0) <= 0.0:  # (a walk that is also the run has its stride by now)
            stride = stride_from_feet(character, character.clip(name))
            if stride is not None:
                strides[name] = stride
                measured.append(name)
    mask_row = 0 if upper_body_mask(character.skeleton) is not None else -1
    heads = len({m.piece for m in character.meshes if m.group == "head"})
    weapons = len(character.props) if character.armed else 0
    motion = Motion.from_bake(bake, roles, strides, mask_row, heads, weapons, clip_speed)
    notes = motion.notes + tuple(f"clip {name!r} has no stride; measured from its planted feet: {strides[name]:.3f} m a cycle"
                                 for name in measured)
    stands = character.clip(roles["idle"]) if roles.get("idle") else None
    return dataclasses.replace(motion, pivots=pivot_table(character, roles), notes=notes, footprint=footprint_radius(character, stands))


def _feet_over_cycle(character, clip, samples: int) -> tuple[np.ndarray, np.ndarray] | None:
    """A clip's foot joints at samples + 1 evenly spaced phases from 0 to 1 (float64 forward kinematics):
    their model-space positions (samples + 1, K, 3) and whether each is on the ground, within the contact
    height of its own lowest point; None for a skeleton without joints named like feet."""
    skeleton = character.skeleton
    feet = foot_joints(skeleton)
    if not feet:
        return None
    g = global_matrices(skeleton, sample_clip(skeleton, clip, np.linspace(0.0, 1.0, samples + 1)))
    pos = g[:, feet][..., :3, 3]
    return pos, pos[..., 1] - pos[..., 1].min(axis=0) <= CONTACT_M


def stride_from_feet(character, clip, samples: int = 240) -> float | None:
    """Metres a cycle the body of an in-place locomotion clip covers, measured from its feet: while a
    foot joint is within the contact height of its lowest point, it carries weight, and the body should
    move forward (+Z, the character's front) as fast as that foot moves back. The stride is the one that
    leaves the least slide in world space per metre walked, summed over every foot joint and contact
    step: the foot-skate measure itself (crowd.anim.foot_skate). None when the skeleton has no joint
    named like a foot or its feet are never on the ground. Clips that travel (root motion) have their
    stride from crowd.asset.root_motion instead."""
    cycle = _feet_over_cycle(character, clip, samples)
    if cycle is None:
        return None
    pos, down = cycle
    both = down[1:] & down[:-1]
    if np.count_nonzero(both) < max(8, samples // 20):
        return None
    step = np.diff(pos, axis=0)[both]  # (steps, 3) model-space moves of feet on the ground
    dx, dz = step[:, 0], step[:, 2]

    def slide(stride):  # metres slid in world space per metre walked, walking `stride` metres a cycle
        return np.hypot(dx, dz + stride / samples).sum() / stride

    # Over the strides the feet's own backward moves span, the slide per metre falls as the stride nears
    # the stance feet's speed and rises past it.
    stride, least = golden_section_max(lambda x: -slide(x), 1e-3, max(float(-dz.min()) * samples, 2e-3), 60)
    return stride if np.isfinite(least) else None


def pivot_table(character, roles: dict) -> np.ndarray | None:
    """Motion.pivots from the character's own clips (float64 forward kinematics), or None for a
    skeleton without joints named like feet."""
    if not foot_joints(character.skeleton):
        return None
    table = np.zeros((3, FOOT_SAMPLES + 1, 3))
    for r, role in enumerate(("idle", "walk", "run")):
        if roles.get(role):
            pos, down = _feet_over_cycle(character, character.clip(roles[role]), FOOT_SAMPLES)
            count = down.sum(axis=1)
            share = down / np.maximum(count, 1)[:, None]
            table[r, :, 0] = (share * pos[..., 0]).sum(axis=1)
            table[r, :, 1] = (share * pos[..., 2]).sum(axis=1)
            table[r, :, 2] = count > 0
    return table
