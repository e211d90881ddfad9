"""Issue 40, point 1: the meshes that can share one draw are merged at import (crowd.asset.merge), and
nothing the draw makes of them changes: the same vertex records, triangles and morph deltas, the same
picture. Modular characters from tests/gltf_factory.py (40 and 200 pieces) merge to the draws their
textures, morph sets and variation choices need.
"""

from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np
import pytest

from conftest import khronos_issues, shared_files
from crowd.asset.gltf import load_character
from crowd.asset.merge import merge_pieces, meshes_per_lod
from crowd.asset.model import PACKED_UV_SPAN, SkinnedMesh, Texture
from crowd.draw.render import Camera, CrowdRenderer, Instances, pack_colors, pack_vertices, unpack_uvs, uv_box
from gltf_factory import make_gltf, modular_gltf

MODULAR = {  # generated files: name -> modular_gltf's arguments
    "modular": dict(pieces=40, groups={"head": 3}, primitives_per_mesh=2, lods=3),
    "modular_morph": dict(pieces=24, apart="morph", primitives_per_mesh=2, lods=2),
    "modular_texture": dict(pieces=40, apart="texture", lods=2),
}
MODELS = [None, "brute", "survivor", *shared_files(), *MODULAR]


def _name(model) -> str:
    return "zombie" if model is None else getattr(model, "name", model)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("modular")


def _load(model, folder, merge=True):
    if model in MODULAR:
        return load_character(modular_gltf(folder / model, **MODULAR[model]), merge=merge)
    return load_character(model, merge=merge)


# -- lossless


@pytest.mark.parametrize("model", MODELS, ids=_name)
def test_merged_meshes_hold_their_sources_vertex_records_triangles_and_deltas(model, folder):
    """Each merged mesh is its sources one after another: their packed vertex records (position,
    normal, joints, weights, colour with the base colour in it), their triangles moved by the vertices
    before them, their morph deltas; every other mesh is as it was. Texture coordinates are the sources'
    float32 ones; packed, they lie on the grid of the merged box (within half its step)."""
    whole, apart = _load(model, folder), _load(model, folder, merge=False)
    by_name = {m.name: m for m in apart.meshes}
    assert len(by_name) == len(apart.meshes)
    merged = {m.name: m for m in whole.merged}
    used = []
    for mesh in whole.meshes:
        sources = [by_name[n] for n in merged[mesh.name].sources] if mesh.name in merged else [by_name[mesh.name]]
        used += [s.name for s in sources]
        assert {(s.lod, s.group, s.piece if s.group else "", s.texture) for s in sources} == {(mesh.lod, mesh.group, mesh.piece if mesh.group else "", mesh.texture)}
        assert (mesh.name, mesh.piece) == (sources[0].name, sources[0].piece)
        records, expected = pack_vertices(mesh), np.concatenate([pack_vertices(s) for s in sources])
        if mesh.texture >= 0:
            np.testing.assert_array_equal(mesh.uvs, np.concatenate([s.uvs for s in sources]))
            if "position_uv" in records.dtype.names:  # the packed layout: the coordinate beside the position
                corner, size = uv_box(mesh.uvs)
                assert np.max(np.abs(unpack_uvs(records["position_uv"][:, 3], corner, size) - mesh.uvs)) <= np.max(size) / 65535 / 2 + 1e-7
                records["position_uv"][:, 3] = expected["position_uv"][:, 3] = 0
        assert records.dtype == expected.dtype
        np.testing.assert_array_equal(records, expected)
        starts = np.cumsum([0] + [len(s.positions) for s in sources[:-1]])
        np.testing.assert_array_equal(mesh.indices, np.concatenate([s.indices + k for s, k in zip(sources, starts)]))
        assert (mesh.morph_targets is None) == all(s.morph_targets is None for s in sources)
        if mesh.morph_targets is not None:
            assert all(np.array_equal(s.morph_targets, mesh.morph_targets) for s in sources)
            for attr in ("morph_positions", "morph_normals"):
                np.testing.assert_array_equal(getattr(mesh, attr), np.concatenate([getattr(s, attr) for s in sources], axis=1))
    assert sorted(used) == sorted(by_name)  # every mesh of the file, once
    before, after = Counter(m.lod for m in apart.meshes), Counter(m.lod for m in whole.meshes)
    assert meshes_per_lod(whole) == {lod: (before[lod], after[lod]) for lod in sorted(before)}


SIZE = (320, 240)


def _picture(ctx, character, shadows=True) -> tuple[np.ndarray, int]:
    """A crowd of 12 agents of `character` walking away from the camera (every LOD, every variation
    choice in turn, each at its own phase), drawn on the CPU cull path; the picture and the draw count."""
    from crowd.anim.bake import bake
    from crowd.anim.processor import AnimationProcessor
    from crowd.frame import CLIP, PHASE, WEIGHT, empty_layers
    from crowd.gl import Offscreen

    n = 12
    rng = np.random.default_rng(1)
    baked = bake(character.skeleton, character.clips)
    with AnimationProcessor(ctx, baked, 4) as proc, Offscreen(ctx, SIZE) as target:
        proc.resize(n)
        layers = empty_layers(n, 4)
        layers[:, 0, CLIP] = np.arange(n) % len(baked.clips)
        layers[:, 0, PHASE] = rng.uniform(0.0, 1.0, n)
        layers[:, 0, WEIGHT] = 1.0
        proc.process(layers)
        with CrowdRenderer(ctx, character, lod_distances=(4.0, 7.0, 11.0), shadows=shadows, culling=True, cull_path="cpu") as renderer:
            choices = {group: np.arange(n) % len(pieces) for group, pieces in renderer.groups[0].items()}
            instances = Instances(np.column_stack([np.linspace(-3.0, 3.0, n), np.zeros(n), -np.linspace(0.0, 14.0, n)]),
                                  rng.uniform(-3.0, 3.0, n).astype(np.float32), np.ones(n, np.float32), np.full((n, 4), 255, np.uint8), choices)
            camera = Camera(eye=np.array([0.0, 1.6, 3.5]), target=np.array([0.0, 1.0, -4.0]), aspect=SIZE[0] / SIZE[1])
            view = renderer.prepare(camera, instances)
            fb = target.framebuffer
            fb.use()
            fb.clear(0.5, 0.5, 0.5, 1.0, depth=1.0)
            if shadows:
                renderer.shadow_pass(view, proc)
            renderer.color_pass(fb, view, proc)
            renderer.ground_pass(fb, view)
            ctx.finish()
            return target.image().astype(int), len(renderer.draws)


def _drawn_in_reverse(character):
    """`character` with its pieces renamed so that the renderer, which orders a character's draws by
    piece name, draws them in the reverse order (variation choices keep their order: first met, first)."""
    names = sorted({m.piece for m in character.meshes})
    rank = {piece: f"{len(names) - k:05d}:{piece}" for k, piece in enumerate(names)}
    return dataclasses.replace(character, meshes=[dataclasses.replace(m, piece=rank[m.piece]) for m in character.meshes])


@pytest.mark.parametrize("model", MODELS, ids=_name)
def test_the_merged_crowd_is_the_same_picture(model, folder, gl_context):
    """The same picture, but where two of the file's own surfaces lie at the same depth: there the one
    drawn first wins, and merging changes the order (so does the renderer's own order of draws, which
    goes by piece name). Such a pixel must change with the unmerged draws' order too, and show one of
    the two (the Witch has one)."""
    whole, apart = _load(model, folder), _load(model, folder, merge=False)
    picture, draws = _picture(gl_context, whole)
    before, draws_before = _picture(gl_context, apart)
    assert draws == len(whole.meshes) and draws_before == len(apart.meshes)
    assert (np.abs(picture - picture[:1, :1]).max(axis=2) > 12).mean() > 0.01  # the crowd is in the picture
    differ = (picture != before).any(axis=2)
    if differ.any():
        reverse, _ = _picture(gl_context, _drawn_in_reverse(apart))
        tied = (reverse != before).any(axis=2)
        assert not np.any(differ & ~tied), f"{int(np.sum(differ & ~tied))} pixels differ that no order of draws explains"
        assert np.all((picture == before).all(axis=2) | (picture == reverse).all(axis=2))
        assert differ.mean() < 1e-4


# -- what merges


def test_the_built_ins_wear_their_shirt_in_their_body_draw_and_keep_their_heads_apart():
    for name in ("zombie", "brute", "survivor"):
        character = load_character(name)
        assert meshes_per_lod(character) == {0: (4, 3), 1: (4, 3), 2: (4, 3), 3: (2, 2), 4: (1, 1)}, name
        assert [(m.lod, m.piece, m.sources) for m in character.merged] == [
            (lod, "body", (f"{name}_body_lod{lod}", f"{name}_shirt_torn_lod{lod}")) for lod in (0, 1, 2)]
        assert sorted({m.piece for m in character.meshes if m.group == "head"}) == ["head_a", "head_b"]


def test_a_modular_character_of_thirteen_pieces_over_six_colours_is_one_draw():
    from conftest import shared

    character = load_character(shared("Quaternius_ModularWomen_Witch.gltf"))
    assert meshes_per_lod(character) == {0: (13, 1)}
    assert character.meshes[0].base_color == (1.0, 1.0, 1.0, 1.0) and not any("merge" in w for w in character.warnings)


@pytest.fixture(scope="module")
def small():
    """A 3-joint character from gltf_factory, its meshes to be replaced by each test's."""
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        character = load_character(make_gltf(Path(folder)), merge=False)
    pixels = np.full((2, 2, 4), 200, np.uint8)
    return dataclasses.replace(character, textures=[Texture("a", pixels), Texture("b", pixels)], morphs=("x", "y"),
                               morph_defaults=np.zeros(2), warnings=[])


def _mesh(name, piece=None, lod=0, group="", texture=-1, morphs=None, base=(1.0, 1.0, 1.0, 1.0), colors=None, uvs=None):
    """A triangle on joint 0."""
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    targets = None if morphs is None else np.array(morphs, np.int64)
    deltas = None if morphs is None else np.full((len(morphs), 3, 3), 0.25, np.float32)
    return SkinnedMesh(name, piece or name, lod, positions, np.tile(np.float32([0, 0, 1]), (3, 1)), np.zeros((3, 4), np.uint16),
                       np.tile(np.float32([1, 0, 0, 0]), (3, 1)), np.arange(3, dtype=np.uint32), colors, base, group, texture,
                       None if texture < 0 else (np.zeros((3, 2), np.float32) if uvs is None else np.asarray(uvs, np.float32)),
                       targets, deltas, None if morphs is None else np.zeros_like(deltas))


def _merged(small, meshes):
    character = merge_pieces(dataclasses.replace(small, meshes=meshes, merged=[]))
    return [(m.name, m.lod) for m in character.meshes], [merge.sources for merge in character.merged]


def test_variation_choices_merge_only_with_their_own_primitives(small):
    meshes = [_mesh("body"), _mesh("head_a#0", "head_a", group="head"), _mesh("belt"), _mesh("head_b", group="head"),
              _mesh("head_a#1", "head_a", group="head"), _mesh("hat_a", group="hat")]
    names, sources = _merged(small, meshes)
    assert names == [("body", 0), ("head_a#0", 0), ("head_b", 0), ("hat_a", 0)]
    assert sources == [("body", "belt"), ("head_a#0", "head_a#1")]


def test_lods_textures_and_morph_sets_keep_meshes_apart(small):
    meshes = [_mesh("a"), _mesh("b", lod=1), _mesh("c", texture=0), _mesh("d", texture=1), _mesh("e", morphs=[0]),
              _mesh("f", morphs=[0, 1]), _mesh("g", morphs=[1, 0]), _mesh("h", texture=1), _mesh("i", morphs=[0]), _mesh("j", lod=1)]
    names, sources = _merged(small, meshes)
    assert sources == [("b", "j"), ("d", "h"), ("e", "i")]
    assert [n for n, _ in names] == ["a", "b", "c", "d", "e", "f", "g"]


def test_a_merged_piece_keeps_its_first_sources_name_at_every_lod(small):
    meshes = [_mesh(f"{piece}_lod{lod}", piece, lod) for lod in range(3) for piece in ("body", "shirt", "boots") if (piece, lod) != ("body", 2)]
    character = merge_pieces(dataclasses.replace(small, meshes=meshes))
    assert [(m.piece, m.lod) for m in character.meshes] == [("body", 0), ("body", 1), ("shirt", 2)]
    assert [m.piece for m in character.merged] == ["body", "body", "shirt"]
    assert meshes_per_lod(character) == {0: (3, 1), 1: (3, 1), 2: (2, 1)}


def test_base_colours_go_into_the_vertex_colours_as_the_draw_multiplies_them(small):
    rng = np.random.default_rng(7)
    meshes = [_mesh("plain"), _mesh("red", base=(0.9, 0.1, 0.1, 1.0)),
              _mesh("painted", base=(0.3, 0.6, 0.9, 0.5), colors=rng.uniform(0, 1, (3, 4)).astype(np.float32)),
              _mesh("dark", base=tuple(float(x) for x in rng.uniform(0, 1, 4)))]
    one = merge_pieces(dataclasses.replace(small, meshes=meshes)).meshes[0]
    assert one.base_color == (1.0, 1.0, 1.0, 1.0) and one.colors.dtype == np.float32
    np.testing.assert_array_equal(pack_colors(one.colors, one.base_color, 12),
                                  np.concatenate([pack_colors(m.colors, m.base_color, 3) for m in meshes]))
    # One base colour among them: it stays the mesh's, and sources without colours are white.
    same = [_mesh("a", base=(0.5, 0.5, 0.5, 1.0)), _mesh("b", base=(0.5, 0.5, 0.5, 1.0), colors=np.full((3, 4), 0.5, np.float32))]
    one = merge_pieces(dataclasses.replace(small, meshes=same)).meshes[0]
    assert one.base_color == (0.5, 0.5, 0.5, 1.0)
    np.testing.assert_array_equal(one.colors, np.concatenate([np.ones((3, 4), np.float32), np.full((3, 4), 0.5, np.float32)]))
    none = merge_pieces(dataclasses.replace(small, meshes=[_mesh("a"), _mesh("b")])).meshes[0]
    assert none.colors is None


def test_textured_meshes_merge_only_where_their_coordinates_keep_their_layout(small):
    span = PACKED_UV_SPAN
    near = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]
    far = [[span - 1.0, 0.0], [span - 0.5, 0.0], [span, 1.0]]
    beyond = [[span + 1.0, 0.0], [span + 2.0, 0.0], [span + 1.5, 1.0]]
    wide = [[0.0, 0.0], [span + 5.0, 0.0], [0.0, 1.0]]
    meshes = [_mesh("a", texture=0, uvs=near), _mesh("b", texture=0, uvs=beyond), _mesh("c", texture=0, uvs=far),
              _mesh("d", texture=0, uvs=wide), _mesh("e", texture=0, uvs=wide)]
    names, sources = _merged(small, meshes)
    # a and c pack together (span 16); b packs alone but not with them; d and e are wide either way.
    assert sources == [("a", "c"), ("d", "e")] and [n for n, _ in names] == ["a", "b", "d"]


def test_a_character_with_nothing_to_merge_is_returned_as_it_is(small):
    character = dataclasses.replace(small, meshes=[_mesh("a"), _mesh("b", texture=0)])
    assert merge_pieces(character) is character and character.merged == []


# -- generated modular characters (tests/gltf_factory.py modular_gltf)


@pytest.mark.parametrize("pieces", [40, 200])
@pytest.mark.parametrize("apart", [None, "texture", "morph"])
def test_modular_characters_of_40_and_200_pieces_merge_to_the_draws_they_need(pieces, apart, tmp_path, gl_context):
    """Mergeable (flat colours): one draw a LOD for the common pieces and one a variation choice.
    Unmergeable (each its own texture, or its own morph targets): every piece its own draw."""
    groups = {"head": 3} if apart is None else None
    path = modular_gltf(tmp_path, pieces=pieces, apart=apart, groups=groups, lods=2)
    character = load_character(path)  # validated on the way
    draws = 1 + 3 if apart is None else pieces
    assert meshes_per_lod(character) == {0: (pieces, draws), 1: (pieces, draws)}
    assert len(character.textures) == (pieces if apart == "texture" else 0)
    assert len(character.morphs) == (pieces if apart == "morph" else 0)
    assert not character.warnings
    with CrowdRenderer(gl_context, character, shadows=False, cull_path="cpu") as renderer:
        assert len(renderer.draws) == 2 * draws
        assert renderer.groups[0] == ({"head": ["head_a", "head_b", "head_c"]} if groups else {})


def test_a_modular_characters_pieces_share_their_meshs_morph_targets(tmp_path):
    path = modular_gltf(tmp_path, pieces=12, joints=20, apart="morph", primitives_per_mesh=2, lods=2)
    character = load_character(path)
    assert meshes_per_lod(character) == {0: (12, 6), 1: (12, 6)} and len(character.skeleton.names) == 20
    assert len(character.morphs) == 6 and any(c.morph_channels for c in character.clips)


@pytest.mark.parametrize("arguments", [dict(pieces=40), dict(pieces=40, apart="texture", lods=2),
                                       dict(pieces=40, apart="morph", lods=2), MODULAR["modular"]], ids=str)
def test_the_khronos_validator_passes_the_modular_files(arguments, tmp_path):
    issues = khronos_issues(modular_gltf(tmp_path, **arguments))
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0 and issues["numInfos"] == 0, issues["messages"][:5]
