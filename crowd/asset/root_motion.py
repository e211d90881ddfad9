"""Root motion taken out of looping clips and kept as their stride.

Exporters (Mixamo, Blender's NLA) often write a walk that travels: the root joint moves forward a
stride per cycle. The crowd moves each agent itself, by the AI's speed along its heading, and keeps the
clip's phase in step with that speed through the clip's stride (metres per cycle), so the feet stay
planted. Left in, root motion would move the body twice and snap it back at every loop. So for every
looping clip whose root joints travel horizontally more than ROOT_MOTION_MIN (a share of the skeleton's
size) over one cycle, the travel is taken out of the root's translation keys as a straight line in time
(what is left is the in-place motion: bob and sway, periodic, so the loop closes) and, where the clip
had no stride, its length becomes the stride. Vertical travel is kept (a clip may climb). One-shot
clips (a lunge, a fall) keep their motion. Each clip changed is one warning.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .model import Character, Clip
from .pose import sample_channel

ROOT_MOTION_MIN = 0.01  # share of the rest skeleton's size: less travel than this is jitter, not motion


def _skeleton_size(character: Character) -> float:
    bind = np.linalg.inv(np.asarray(character.skeleton.inverse_bind, np.float64))[:, :3, 3]
    return float(np.max(bind.max(axis=0) - bind.min(axis=0))) if len(bind) else 0.0


def _in_place(clip: Clip, roots: set[int], least: float) -> tuple[Clip, float] | None:
    """The clip without its roots' horizontal travel, and that travel per cycle; None when it has none."""
    travel, moved = 0.0, []
    for index, ch in enumerate(clip.channels):
        if ch.path != "translation" or ch.joint not in roots or clip.duration <= 0:
            continue
        ends = sample_channel(ch, np.array([clip.start, clip.end]))
        drift = ends[1] - ends[0]
        drift[1] = 0.0  # up: kept
        length = float(np.linalg.norm(drift))
        if length <= least:
            continue
        rate = drift / clip.duration  # metres per second along the travel
        values = np.array(ch.values, np.float64, copy=True)
        offsets = (np.clip(ch.times, clip.start, clip.end) - clip.start)[:, None] * rate
        if values.ndim == 3:  # CUBICSPLINE: (in tangent, value, out tangent); tangents are per second
            values[:, 1] -= offsets
            values[:, 0] -= rate
            values[:, 2] -= rate
        else:
            values -= offsets
        moved.append((index, dataclasses.replace(ch, values=values)))
        travel = max(travel, length)
    if not moved:
        return None
    channels = list(clip.channels)
    for index, ch in moved:
        channels[index] = ch
    return dataclasses.replace(clip, channels=channels, stride=clip.stride if clip.stride is not None else travel), travel


def take_out_root_motion(character: Character) -> Character:
    roots = set(np.flatnonzero(np.asarray(character.skeleton.parents) < 0).tolist())
    least = ROOT_MOTION_MIN * _skeleton_size(character)
    clips, warnings = [], list(character.warnings)
    for clip in character.clips:
        found = _in_place(clip, roots, least) if clip.loop else None
        if found is None:
            clips.append(clip)
            continue
        clip, travel = found
        clips.append(clip)
        warnings.append(f"clip {clip.name!r}: its root travels {travel:.3g} per cycle; taken out of the pose and used as its stride")
    if len(warnings) == len(character.warnings):  # no clip travelled
        return character
    return dataclasses.replace(character, clips=clips, warnings=warnings)
