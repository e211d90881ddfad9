"""Characters of many pieces on every cull path (issue 40, points 1 and 5): generated files of 40 and 200
pieces that cannot share a draw (each its own texture, or its own morph targets), with a variation group
and a coarser LOD, drawn by the compute, the transform-feedback and the numpy culls: the same picture and
the same counts on each, and every piece's draw fed. Files whose pieces can share a draw merge into one
draw a LOD."""

from __future__ import annotations

import numpy as np
import pytest

from crowd.asset.gltf import load_character
from crowd.gl import Offscreen, has_compute
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import CharacterSpec, PipelineConfig
from crowd.sim.config import AIConfig
from gltf_factory import modular_gltf

SIZE = (320, 180)


def _frames(gl_context, path, cull: str):
    config = PipelineConfig(agents=80, seed=3, characters=(CharacterSpec(str(path), 1.0),), cull=cull, ai_path="cpu", gl="4.1" if cull == "feedback" else "auto",
                            survivor=False, impostors="off", lod_distances=(12.0, 30.0, 60.0), ai=AIConfig(half_extent=10.0))
    with Offscreen(gl_context, SIZE) as target, CrowdPipeline(gl_context, config) as p:
        p.camera = p.overview_camera(SIZE[0] / SIZE[1])
        for _ in range(3):
            p.frame(target.framebuffer, 1 / 30)
        p.refresh_counts()
        draws = [(d.piece, d.lod, d.count) for d in p.renderer.draws if d.twin_of is None]
        return target.image(), dict(p.renderer.last), draws, p.renderer.gpu_bytes()


@pytest.mark.parametrize("pieces, apart", [(40, "texture"), (200, "texture"), (40, "morph")])
def test_unmergeable_pieces_draw_alike_on_every_cull_path(gl_context, tmp_path, pieces, apart):
    path = modular_gltf(tmp_path, pieces=pieces, joints=48, apart=apart, groups={"head": 3}, lods=2)
    character = load_character(path)
    per_lod = sum(1 for m in character.meshes if m.lod == 0)
    assert per_lod == pieces  # nothing merged: every piece is a draw of its own
    culls = ["cpu", "feedback"] + (["gpu"] if has_compute(gl_context) else [])
    seen = {cull: _frames(gl_context, path, cull) for cull in culls}
    image, last, draws, held = seen["cpu"]
    assert last["instances"] > 2 * pieces and sum(1 for _, _, count in draws if count) >= pieces - 3
    for cull in culls[1:]:
        other_image, other_last, other_draws, other_held = seen[cull]
        assert np.array_equal(image, other_image), cull
        assert other_last == last, cull
        assert sorted(other_draws) == sorted(draws), cull
        # The pieces cost the lists nothing an agent: one list per LOD and choice, not per piece.
        assert other_held["lists"] <= held["records"] * 4, cull


def test_pieces_that_can_share_a_draw_merge_into_one(tmp_path):
    path = modular_gltf(tmp_path, pieces=200, joints=64, materials=12, groups={"head": 4}, lods=2)
    character = load_character(path)
    for lod in (0, 1):
        meshes = [m for m in character.meshes if m.lod == lod]
        assert len([m for m in meshes if not m.group]) == 1 and len([m for m in meshes if m.group == "head"]) == 4
