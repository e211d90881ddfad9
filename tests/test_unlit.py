"""KHR_materials_unlit (issue 44, point 6): a piece whose material is unlit is drawn in its base colour
(through the fog, as everything is), without the sun, sky or shadows; one lit piece beside it keeps its
lighting; a character all of whose pieces are unlit has unlit impostors; an unlit prop is drawn unlit in
the hand; a cast without unlit pieces compiles none of it."""

from __future__ import annotations

import json

import numpy as np
import pytest

import gltf_factory
from crowd.asset.gltf import load_character
from crowd.gl import Offscreen
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import PipelineConfig
from crowd.sim.config import AIConfig

SIZE = (160, 120)
COLOUR = [0.8, 0.3, 0.1, 1.0]


def _character(folder, unlit: bool):
    """The factory's modular figure (flat-shaded boxes on a skeleton), its one material COLOUR, unlit or not."""
    path = gltf_factory.modular_gltf(folder, pieces=24, materials=1, name="unlit.gltf" if unlit else "lit.gltf")
    doc = json.loads(path.read_text())
    doc["materials"] = [{"pbrMetallicRoughness": {"baseColorFactor": COLOUR}}]
    if unlit:
        doc["materials"][0]["extensions"] = {"KHR_materials_unlit": {}}
        doc["extensionsUsed"] = ["KHR_materials_unlit"]
    path.write_text(json.dumps(doc))
    return path


def test_the_importer_reads_the_extension(tmp_path):
    assert all(m.unlit for m in load_character(_character(tmp_path, True)).meshes)
    assert not any(m.unlit for m in load_character(_character(tmp_path, False)).meshes)


def _pixels(gl_context, path, agents: int, impostors: str = "off") -> np.ndarray:
    config = PipelineConfig(model=path, agents=agents, town=False, survivor=False, shadows=False, weapons=False, ai_path="cpu",
                            impostors=impostors, impostor_distance=1.0, ai=AIConfig(half_extent=1.0, wander_speed=0.0))
    with Offscreen(gl_context, SIZE) as target, CrowdPipeline(gl_context, config) as p:
        p.camera = p.overview_camera(SIZE[0] / SIZE[1])
        p.camera = type(p.camera)(eye=(0.0, 1.0, 2.2), target=(0.0, 0.9, 0.0))  # level, near: the agent fills the view's middle
        for _ in range(3):
            p.frame(target.framebuffer, 0.0)
        assert p.renderer.unlit_pieces == ("unlit" in path.name)
        return np.frombuffer(target.framebuffer.read(), np.uint8).reshape(SIZE[1], SIZE[0], 3).astype(np.int64)


@pytest.mark.parametrize("impostors", ["off", "on"])
def test_an_unlit_character_is_one_colour_and_a_lit_one_is_shaded(gl_context, tmp_path, impostors):
    spreads = {}
    for unlit in (False, True):
        path = _character(tmp_path, unlit)
        empty, drawn = _pixels(gl_context, path, 0, impostors), _pixels(gl_context, path, 1, impostors)
        mask = np.any(drawn != empty, axis=2)
        assert mask.sum() > 200, mask.sum()  # the agent covers pixels
        colours = drawn[mask]
        spreads[unlit] = int((colours.max(axis=0) - colours.min(axis=0)).max())
    # Lit: the sun and sky shade the faces apart; unlit: one colour, bar the fog's few metres and the edges' blend.
    assert spreads[False] > 40 and spreads[True] <= 12, spreads


def _zombie_with_prop(folder, unlit: bool):
    """The built-in zombie with its props one colour (COLOUR, no vertex colours), their material unlit or not."""
    from crowd.asset.zombie import ASSET_PATH

    doc, blob = gltf_factory.glb_parts(ASSET_PATH)
    prop_material = next(i for i, m in enumerate(doc["materials"]) if m.get("name") == "prop")
    doc["materials"][prop_material]["pbrMetallicRoughness"]["baseColorFactor"] = COLOUR
    if unlit:
        doc["materials"][prop_material]["extensions"] = {"KHR_materials_unlit": {}}
        doc["extensionsUsed"] = sorted(set(doc.get("extensionsUsed", [])) | {"KHR_materials_unlit"})
    for node in doc["nodes"]:
        if "prop" in ((node.get("extras") or {}).get("crowd") or {}):
            for prim in doc["meshes"][node["mesh"]]["primitives"]:
                prim["attributes"].pop("COLOR_0", None)
    return gltf_factory.write_glb(folder / ("prop_unlit.glb" if unlit else "prop_lit.glb"), doc, blob)


def _weapon_pixels(gl_context, path) -> np.ndarray:
    """The colours of the pixels the one armed agent's weapon covers (the frame with weapons against without)."""
    frames = []
    for weapons in (False, True):
        config = PipelineConfig(model=path, agents=1, town=False, survivor=False, shadows=False, weapons=weapons, ai_path="cpu",
                                ai=AIConfig(half_extent=1.0, wander_speed=0.0, armed_share=1.0))
        with Offscreen(gl_context, SIZE) as target, CrowdPipeline(gl_context, config) as p:
            p.camera = type(p.overview_camera(SIZE[0] / SIZE[1]))(eye=(0.0, 1.0, 1.6), target=(0.0, 0.8, 0.0))
            for _ in range(3):
                p.frame(target.framebuffer, 0.0)
            frames.append(np.frombuffer(target.framebuffer.read(), np.uint8).reshape(SIZE[1], SIZE[0], 3).astype(np.int64))
    mask = np.any(frames[0] != frames[1], axis=2)
    assert mask.sum() > 60, mask.sum()  # the weapon covers pixels
    return frames[1][mask]


def test_an_unlit_prop_is_one_colour_and_a_lit_one_is_shaded(gl_context, tmp_path):
    assert all(m.unlit for prop in load_character(_zombie_with_prop(tmp_path, True)).props.values() for m in prop.lods)
    spreads = {}
    for unlit in (False, True):
        colours = _weapon_pixels(gl_context, _zombie_with_prop(tmp_path, unlit))
        spreads[unlit] = int((colours.max(axis=0) - colours.min(axis=0)).max())
    assert spreads[False] > 40 and spreads[True] <= 12, spreads


def test_an_unlit_prop_is_unlit_in_its_impostors_hand_too(tmp_path):
    """Past the impostor distance the weapon is a skinned piece of the impostor's LOD (held_pieces): it
    keeps its material's unlit flag, so it does not turn lit where the body turns into an impostor."""
    from crowd.draw.impostors import held_pieces

    for unlit in (False, True):
        pieces = held_pieces(load_character(_zombie_with_prop(tmp_path, unlit)), 4)
        assert pieces and all(p.unlit == unlit for p in pieces)
