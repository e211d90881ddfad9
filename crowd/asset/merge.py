"""Pieces that can share one draw, merged at import (issue 40, point 1): a modular character's dozens of
meshes become the few draws its materials need, which every cull path takes and which cost fewer calls.

Two skinned meshes of a character can be one draw when the draw stage would draw them alike: the same
LOD, the same choice (both worn by every agent, or both the same piece of one variation group), the same
base-colour texture (or none), the same morph targets, and the same vertex layout. Every mesh of a
Character shares its skeleton, and the only material state a mesh carries is its base colour factor and
its texture: alpha modes and the other maps are left out at import (crowd.asset.gltf.materials). The
base colour factor is no reason to keep meshes apart: the draw multiplies it into each vertex's colour
before quantising to RGBA8 (crowd.draw.render.pack_colors), so merged meshes whose factors differ carry
it in their vertex colours instead, computed in float32 as the draw computes it, and draw to the same
bytes.

A merged mesh holds its sources' vertices in order, one source after another (file order), each source's
triangles after the ones before, their indices moved by the vertices before them; morph deltas are
joined the same way. It takes the name, piece and group of its first source in file order, so the same
sources make a piece of the same name at every LOD (the draw stage matches a piece across LODs by its
name). ``Character.merged`` records each merge; ``meshes_per_lod`` says how many meshes each LOD had
before and after.

Textured meshes merge only where the draw keeps their vertex layout: the draw packs a piece's texture
coordinates as unorm16 across the box they span when that span is at most PACKED_UV_SPAN, else it keeps
them as floats (a wider, slower vertex). Meshes whose coordinates pack on their own but not together stay
apart. Packed coordinates of merged meshes lie on the grid of the union's box, at most half its step
(span / 65535 / 2) from the coordinates; those of each source alone, on its own box's grid.
"""

from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np

from .model import PACKED_UV_SPAN, Character, MergedMesh, SkinnedMesh


def merge_pieces(character: Character) -> Character:
    """`character` with each set of its meshes that can share one draw made one mesh (the module
    docstring says which and how); the same character when no two meshes can."""
    sets: dict[tuple, list[int]] = {}
    for i, mesh in enumerate(character.meshes):
        sets.setdefault(_draw_key(mesh), []).append(i)
    joined = _joinable(character.meshes, list(sets.values()))
    if all(len(members) == 1 for members in joined):
        return character
    meshes, merged = [], []
    for members in sorted(joined):
        sources = [character.meshes[i] for i in members]
        if len(sources) == 1:
            meshes.append(sources[0])
            continue
        meshes.append(_joined(sources))
        merged.append(MergedMesh(sources[0].lod, sources[0].piece, sources[0].name, tuple(m.name for m in sources)))
    return dataclasses.replace(character, meshes=meshes, merged=[*character.merged, *merged], warnings=list(character.warnings)).validate()


def meshes_per_lod(character: Character) -> dict[int, tuple[int, int]]:
    """Per LOD, (meshes the file had, meshes after merging): the draws a character of that LOD costs."""
    after = Counter(m.lod for m in character.meshes)
    joined = Counter()
    for merge in character.merged:
        joined[merge.lod] += len(merge.sources) - 1
    return {lod: (after[lod] + joined[lod], after[lod]) for lod in sorted(after)}


def _draw_key(mesh: SkinnedMesh) -> tuple:
    """What must be equal for two meshes to share a draw (all but the texture coordinates' span)."""
    choice = (mesh.group, mesh.piece) if mesh.group else ("", "")
    morphs = None if mesh.morph_targets is None else tuple(int(t) for t in mesh.morph_targets)
    return mesh.lod, choice, mesh.texture, morphs, mesh.unlit


def _uv_span(mesh: SkinnedMesh) -> tuple[np.ndarray, np.ndarray]:
    uv = np.asarray(mesh.uvs, np.float64)
    return uv.min(axis=0), uv.max(axis=0)


def _packed(low: np.ndarray, high: np.ndarray) -> bool:
    return float(np.max(high - low)) <= PACKED_UV_SPAN


def _joinable(meshes: list[SkinnedMesh], sets: list[list[int]]) -> list[list[int]]:
    """The sets split where texture coordinates would change layout together: a textured mesh joins the
    first run of its set whose layout the union keeps (meshes in file order)."""
    out = []
    for members in sets:
        if meshes[members[0]].texture < 0:
            out.append(members)
            continue
        runs: list[tuple[list[int], np.ndarray, np.ndarray, bool]] = []
        for i in members:
            low, high = _uv_span(meshes[i])
            packed = _packed(low, high)
            for k, (run, run_low, run_high, run_packed) in enumerate(runs):
                union_low, union_high = np.minimum(run_low, low), np.maximum(run_high, high)
                if packed == run_packed == _packed(union_low, union_high):
                    runs[k] = ([*run, i], union_low, union_high, run_packed)
                    break
            else:
                runs.append(([i], low, high, packed))
        out += [run for run, *_ in runs]
    return out


def _joined(sources: list[SkinnedMesh]) -> SkinnedMesh:
    first = sources[0]
    starts = np.cumsum([0] + [len(m.positions) for m in sources[:-1]])
    one_colour = len({tuple(m.base_color) for m in sources}) == 1
    if one_colour and all(m.colors is None for m in sources):
        colors, base = None, first.base_color
    elif one_colour:
        colors, base = np.concatenate([_vertex_colors(m) for m in sources]), first.base_color
    else:  # each source's factor in its colours, as the draw multiplies them (float32)
        colors = np.concatenate([_vertex_colors(m) * np.asarray(m.base_color, np.float32) for m in sources])
        base = (1.0, 1.0, 1.0, 1.0)
    morphing = first.morph_targets is not None
    return SkinnedMesh(
        name=first.name, piece=first.piece, lod=first.lod, group=first.group,
        positions=np.concatenate([m.positions for m in sources]), normals=np.concatenate([m.normals for m in sources]),
        joints=np.concatenate([m.joints for m in sources]), weights=np.concatenate([m.weights for m in sources]),
        indices=np.concatenate([m.indices.astype(np.uint32) + np.uint32(k) for m, k in zip(sources, starts)]),
        colors=colors, base_color=base, texture=first.texture, unlit=first.unlit,
        uvs=np.concatenate([m.uvs for m in sources]) if first.texture >= 0 else None,
        morph_targets=first.morph_targets.copy() if morphing else None,
        morph_positions=np.concatenate([m.morph_positions for m in sources], axis=1) if morphing else None,
        morph_normals=np.concatenate([m.morph_normals for m in sources], axis=1) if morphing else None,
    )


def _vertex_colors(mesh: SkinnedMesh) -> np.ndarray:
    """The mesh's vertex colours as float32, white where it has none (what the draw takes for none)."""
    if mesh.colors is None:
        return np.ones((len(mesh.positions), 4), np.float32)
    return np.asarray(mesh.colors, np.float32)
