"""Issue 18: every real character in ../shared/gltf (skipped when absent), and the built-in zombie,
drawn whole, at a person's size, upright with its feet on the ground, with its texture where it has
one. Pixel tests on one agent seen from the side:
- known joints (the one carrying the most skin weight, and the highest of the pose) project onto
  pixels the body covers;
- the body's height in pixels is within 20 % of its standing height projected at the agent;
- its lowest covered pixel is the ground under the agent (within 10 % of that height), and its head
  joint, where it has one, is in the upper half of the silhouette (up is +Y).
"""

from __future__ import annotations

import numpy as np
import pytest

from conftest import shared_files
from crowd.asset.gltf import load_character
from crowd.asset.units import HUMAN_HEIGHTS, standing_height
from crowd.frame import Camera
from crowd.gl import Offscreen
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import PipelineConfig
from crowd.sim.config import AIConfig
from crowd.smoke import FIXED_DT

SIZE = (480, 480)
MODELS = [None, *shared_files()]


def _name(model) -> str:
    return "zombie" if model is None else model.name


@pytest.mark.parametrize("model", MODELS, ids=_name)
def test_one_character_seen_from_the_side_stands_whole_at_a_persons_size(model, gl_context):
    character = load_character(model)
    height = standing_height(character)
    assert HUMAN_HEIGHTS[0] <= height <= HUMAN_HEIGHTS[1], (height, character.warnings)
    config = PipelineConfig(agents=1, seed=5, shadows=False, weapons=False, model=model, ai=AIConfig(half_extent=2.0))
    with CrowdPipeline(gl_context, config) as pipeline, Offscreen(gl_context, SIZE) as target:
        pipeline.frame(target.framebuffer, FIXED_DT)  # places the agent
        ground = np.array([pipeline.ai.x[0], 0.0, pipeline.ai.z[0]])
        agent_height = height * float(pipeline.ai.scale[0])
        # Looking at the agent from 3.5 of its heights away, level with its middle: the whole body fits.
        pipeline.camera = Camera(eye=ground + [0.0, agent_height * 0.5, agent_height * 3.5],
                                 target=ground + [0.0, agent_height * 0.5, 0.0], aspect=SIZE[0] / SIZE[1])
        for _ in range(2):
            pipeline.frame(target.framebuffer, FIXED_DT)
        drawn = target.image().astype(int)
        joints = np.stack([pipeline.joint_world_positions(j)[0] for j in range(character.skeleton.joint_count)])
        ground = np.array([pipeline.ai.x[0], 0.0, pipeline.ai.z[0]])
        foot, top = pipeline.project(np.array([ground, ground + [0.0, agent_height, 0.0]]), SIZE)
        pixels = pipeline.project(joints, SIZE)
        pipeline.set("agents", 0)
        pipeline.frame(target.framebuffer, FIXED_DT)
        empty = target.image().astype(int)
    covered = np.abs(drawn - empty).max(axis=2) > 12
    assert covered.mean() > 0.01, "the character is not drawn"

    def on_body(x, y, reach=2):
        xi, yi = int(round(x)), int(round(y))
        return covered[max(yi - reach, 0): yi + reach + 1, max(xi - reach, 0): xi + reach + 1].any()

    weight = np.zeros(character.skeleton.joint_count)
    for mesh in character.meshes:
        if mesh.lod == 0:
            np.add.at(weight, mesh.joints.ravel(), mesh.weights.ravel())
    for j in {int(np.argmax(weight)), int(np.argmax(joints[:, 1]))}:
        assert on_body(*pixels[j]), f"joint {character.skeleton.names[j]!r} at pixel {pixels[j]} is not on the body"
    rows = np.flatnonzero(covered.any(axis=1))
    expected = foot[1] - top[1]
    assert rows[-1] - rows[0] + 1 == pytest.approx(expected, rel=0.2)
    assert abs(rows[-1] - foot[1]) < 0.1 * expected, "the feet are not on the ground"
    heads = [j for j, n in enumerate(character.skeleton.names) if "head" in n.lower() and "end" not in n.lower()]
    if heads:
        assert pixels[heads[0], 1] < (rows[0] + rows[-1]) / 2, "the head is in the lower half: the character is upside down"
