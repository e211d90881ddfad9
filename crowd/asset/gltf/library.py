"""Clips from other files (``--clips``, a scene character's ``clips``): a character pack's animation
library, or Mixamo's animations downloaded apart from the character. Their channels are matched to the
character's joints by node name, and their keys are read in the library's own space (its nodes above a
joint folded in, its scale above the root factored out, as the character's own clips are), so clips
exported from the same rig play as the character's own.

What does not carry over is left out, and said once per file: nodes the character has no joint for,
joints of the character the file does not animate (they stay at rest), translation keys of a joint
whose bone the file makes another length (the character's length is kept), and morph weight channels
(they name the library's meshes, not the character's).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..model import Clip, Skeleton
from .clips import read_clips
from .meshes import Morphs
from .reader import GltfImportError, Reader
from .tree import Fold, Tree

BONE_TOLERANCE = 0.01  # a bone whose rest length differs from the character's by more than this share keeps the character's


def read_library(path: Path, skeleton: Skeleton, taken: set[str]) -> tuple[list[Clip], str]:
    """The clips of the glTF file `path` on `skeleton` (the character's, whose clip names `taken` are in
    use: a clash gets the file's name after it), and one line saying what matched. GltfImportError (one
    line, naming the file) for a file that cannot be read or matches no joint."""
    path = Path(path)
    if not path.is_file():
        raise GltfImportError(f"{path}: no such file (a clip library)")
    with np.errstate(invalid="ignore", over="ignore"):
        r = Reader(path)
        tree = Tree(r)
        index = {name: j for j, name in enumerate(skeleton.names)}
        matched: dict[int, int] = {}
        for node, n in enumerate(tree.nodes):
            name = n.get("name")
            if isinstance(name, str) and name in index and index[name] not in matched.values():
                matched[node] = index[name]
        if not matched:
            r.fail(f"no node is named as a joint of the character ({skeleton.joint_count} joints, e.g. {', '.join(skeleton.names[:3])}): "
                   "its clips cannot be matched")
        tree.joints = set(matched)
        folds: list[Fold | None] = [None] * skeleton.joint_count
        for node, j in matched.items():
            above = tree.between(node)
            fold = None if above is None else Fold(above)
            if fold is not None and not fold.identity:
                if not fold.ok:
                    r.fail(f"non-uniform scale or shear on a non-joint node above node {node} ({skeleton.names[j]!r})")
                folds[j] = fold
        roots = [j for node, j in matched.items() if tree.joint_above(node) is None]
        scales = {round(folds[j].s, 9) if folds[j] else 1.0 for j in roots}
        factor = scales.pop() if len(scales) == 1 else 1.0
        notes: list[str] = []
        clips = read_clips(r, tree, skeleton, matched, folds, factor, Morphs(r, []), notes)
    if not clips:
        raise GltfImportError(f"{path.name}: no animation moves a joint of the character")
    kept_length = _keep_bone_lengths(r, skeleton, matched, folds, factor, clips)
    for clip in clips:
        if clip.name in taken:
            clip.name = f"{clip.name}.{path.stem}"
        taken.add(clip.name)
    animated = {ch.joint for clip in clips for ch in clip.channels}
    line = (f"clips from {path.name}: {len(clips)} ({', '.join(c.name for c in clips[:4])}{', ...' if len(clips) > 4 else ''}); "
            f"{len(matched)} of the character's {skeleton.joint_count} joints matched by name, {len(animated)} animated")
    unmatched = sum(1 for n in tree.nodes if isinstance(n.get("name"), str)) - len(matched)
    if unmatched > 0:
        line += f"; {unmatched} named nodes of the file matched no joint"
    if kept_length:
        line += f"; translation keys of {len(kept_length)} joints left out, their bones being another length ({', '.join(kept_length[:3])})"
    morph_notes = [n for n in notes if "morph" in n]
    if morph_notes:
        line += f"; {len(morph_notes)} morph weight channels left out (they name the file's meshes)"
    return clips, line


def _keep_bone_lengths(r: Reader, skeleton: Skeleton, matched: dict[int, int], folds, factor: float, clips: list[Clip]) -> list[str]:
    """Drops the translation channels of non-root joints whose rest offset in the file (in the clips'
    space) is another length than the character's bone; returns those joints' names."""
    rest = np.asarray(skeleton.rest_translation, np.float64)
    longer = []
    for node, j in matched.items():
        if skeleton.parents[j] < 0:
            continue
        t, _, _, _ = r.trs(node)
        t = folds[j].translation(t) if folds[j] is not None else np.asarray(t, np.float64)
        t = t * factor
        size = max(float(np.linalg.norm(rest[j])), 1e-6)
        if abs(float(np.linalg.norm(t)) - float(np.linalg.norm(rest[j]))) > BONE_TOLERANCE * size:
            longer.append(j)
    for clip in clips:
        clip.channels = [ch for ch in clip.channels if not (ch.path == "translation" and ch.joint in longer)]
    return [skeleton.names[j] for j in longer]
