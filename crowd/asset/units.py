"""A character brought to the crowd's world: metres, about a person's height.

glTF says metres, but files are authored in whatever the tool used: a character 80 units tall puts the
camera inside its polygons, and the AI's speeds and strides (metres per second, metres per cycle) make
no sense for it. The standing height is measured from the rest pose, skinned (not from the bind meshes,
which may be in another space or size than what is drawn). A character outside HUMAN_HEIGHTS is
scaled to TARGET_HEIGHT with one warning that says so; a scene's or the command line's ``model_scale``
sets the factor instead ("auto" measures).

Scaling is uniform and exact in meaning: joint translations (rest and keyed), the translations of the
inverse binds, mesh positions and morph position deltas, attachment offsets and prop grips are multiplied
by the factor, and rotations, normals and weights are untouched, so every skinned vertex moves by exactly
that factor.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .model import Character, Clip
from .pose import global_matrices, rest_pose, sample_clip

GROUND_TOLERANCE = 0.05  # share of the height the lowest rest-pose point may lie off the ground (soles sink a little)
HUMAN_HEIGHTS = (0.5, 3.0)  # metres: a character standing between these is taken as authored in metres
TARGET_HEIGHT = 1.8  # metres: what a character outside them is scaled to
AUTO = "auto"


def standing_height(character: Character) -> float:
    """Height (along +Y) of the character's most detailed meshes in the rest pose, skinned."""
    low, high = rest_extent(character)
    return high - low if np.isfinite(high - low) else 0.0


def rest_extent(character: Character) -> tuple[float, float]:
    """Lowest and highest y of the character's most detailed meshes in the rest pose, skinned."""
    low, high = np.inf, -np.inf
    for y in _skinned_rows(character, rest_pose(character.skeleton), 1):
        low, high = min(low, float(y.min(initial=np.inf))), max(high, float(y.max(initial=-np.inf)))
    return low, high


def footprint_radius(character: Character, clip: Clip | None = None) -> float:
    """Metres from the model's vertical axis (where an agent stands) to the farthest point of its most
    detailed meshes, skinned in `clip`'s first pose (how it stands or hovers; the rest pose without one):
    a person's arms, a bat's wingtips."""
    pose = rest_pose(character.skeleton) if clip is None else sample_clip(character.skeleton, clip, np.zeros(1))
    reach = 0.0
    for x, z in _skinned_rows(character, pose, 0, 2):
        reach = max(reach, float(np.sqrt(x * x + z * z).max(initial=0.0)))
    return reach


def _lod0(character: Character):
    lod = min((m.lod for m in character.meshes), default=0)
    return (m for m in character.meshes if m.lod == lod)


def _skinned_rows(character: Character, pose, *axes: int):
    """Per mesh of the most detailed LOD, its vertices' coordinates along each of `axes` (a tuple per mesh
    with several, an array with one), skinned in `pose` by linear blending: the rest pose is where the
    bind meshes came from, so any blend rule gives the same points there, and elsewhere linear blending is
    within millimetres of the drawn dual quaternions for a measure of size."""
    sk = character.skeleton
    joints = global_matrices(sk, pose)[0] @ np.asarray(sk.inverse_bind, np.float64)  # (J, 4, 4)
    for mesh in _lod0(character):
        p = np.c_[np.asarray(mesh.positions, np.float64), np.ones(len(mesh.positions))]
        rows = tuple(np.sum(np.einsum("vkj,vj->vk", joints[mesh.joints.astype(np.int64), axis, :], p) * mesh.weights, axis=1)
                     for axis in axes)
        yield rows[0] if len(rows) == 1 else rows


def lift_character(character: Character, lift: float) -> Character:
    """The same character `lift` metres higher: its root joints' rest and keyed translations move up,
    so every joint, skinned vertex, attachment and prop follows."""
    roots = set(np.flatnonzero(np.asarray(character.skeleton.parents) < 0).tolist())
    up = np.array([0.0, float(lift), 0.0])
    rest = np.asarray(character.skeleton.rest_translation, np.float64).copy()
    rest[sorted(roots)] += up
    skeleton = dataclasses.replace(character.skeleton, rest_translation=rest)

    def clip(c: Clip) -> Clip:
        channels = []
        for ch in c.channels:
            if ch.path == "translation" and ch.joint in roots:
                values = np.array(ch.values, np.float64, copy=True)
                if values.ndim == 3:  # CUBICSPLINE: (in tangent, value, out tangent) per key; only values move
                    values[:, 1] += up
                else:
                    values += up
                ch = dataclasses.replace(ch, values=values)
            channels.append(ch)
        return dataclasses.replace(c, channels=channels)

    return dataclasses.replace(character, skeleton=skeleton, clips=[clip(c) for c in character.clips], warnings=list(character.warnings))


def scale_character(character: Character, factor: float) -> Character:
    """The same character `factor` times as large (see the module docstring for what is scaled)."""
    f = float(factor)

    def moved(matrix: np.ndarray) -> np.ndarray:
        out = np.array(matrix, np.float64, copy=True)
        out[..., :3, 3] *= f
        return out

    sk = character.skeleton
    skeleton = dataclasses.replace(sk, rest_translation=np.asarray(sk.rest_translation, np.float64) * f, inverse_bind=moved(sk.inverse_bind))

    def clip(c: Clip) -> Clip:
        channels = [dataclasses.replace(ch, values=ch.values * f) if ch.path == "translation" else ch for ch in c.channels]
        return dataclasses.replace(c, channels=channels, stride=None if c.stride is None else c.stride * f)

    def rigid(mesh):
        return dataclasses.replace(mesh, positions=(np.asarray(mesh.positions, np.float64) * f).astype(np.float32))

    def skinned(mesh):  # its morph targets' position deltas are lengths too (normal deltas are not)
        deltas = mesh.morph_positions if mesh.morph_positions is None else (np.asarray(mesh.morph_positions, np.float64) * f).astype(np.float32)
        return dataclasses.replace(rigid(mesh), morph_positions=deltas)

    return dataclasses.replace(
        character, skeleton=skeleton,
        meshes=[skinned(m) for m in character.meshes],
        clips=[clip(c) for c in character.clips],
        attachments=[dataclasses.replace(a, mesh=rigid(a.mesh), offset=moved(a.offset)) for a in character.attachments],
        props={name: dataclasses.replace(p, mesh=rigid(p.mesh), grip=moved(p.grip), coarser=tuple(rigid(c) for c in p.coarser))
               for name, p in character.props.items()},
        warnings=list(character.warnings),
        lod_distances=None if character.lod_distances is None else tuple(d * f for d in character.lod_distances))


def to_crowd_units(character: Character, model_scale: float | str = AUTO) -> Character:
    """`character` at the crowd's scale, standing on the ground: `model_scale` times as large, or with
    "auto", scaled to TARGET_HEIGHT when its standing height lies outside HUMAN_HEIGHTS; then lifted or
    lowered onto y = 0 when its lowest rest-pose point lies more than GROUND_TOLERANCE of its height off
    it (a character modelled around its centre). Each change is one warning."""
    if model_scale != AUTO:
        if float(model_scale) != 1.0:
            character = scale_character(character, float(model_scale))
            character.warnings.append(f"scaled by {float(model_scale):g} (model_scale)")
    else:
        height = standing_height(character)
        if height > 0.0 and not HUMAN_HEIGHTS[0] <= height <= HUMAN_HEIGHTS[1]:
            factor = TARGET_HEIGHT / height
            character = scale_character(character, factor)
            character.warnings.append(f"stands {height:.4g} units tall, outside {HUMAN_HEIGHTS[0]:g} to {HUMAN_HEIGHTS[1]:g} m: "
                                      f"scaled by {factor:.4g} to {TARGET_HEIGHT:g} m (model_scale sets the factor)")
    low, high = rest_extent(character)
    if np.isfinite(low) and high > low and abs(low) > GROUND_TOLERANCE * (high - low):
        character = lift_character(character, -low)
        character.warnings.append(f"its feet were {low:+.3g} m off the ground in the rest pose: moved {-low:+.3g} m to stand on it")
    return character
