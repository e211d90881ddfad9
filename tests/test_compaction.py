"""crowd-bench compaction (bench/compaction_probe.py): the prefix-sum compaction fills the same lists
as the runtime's atomics, agent for agent, on a crowd that spans several work groups and LODs."""

import pytest

from crowd.gl import has_compute
from crowd.pipeline import CrowdPipeline
from crowd.scene import Scene


@pytest.mark.parametrize("agents", [1, 700])
def test_prefix_sum_and_atomics_list_the_same_agents(gl_context, agents):
    if not has_compute(gl_context):
        pytest.skip("the GPU cull needs GL 4.3")
    from bench.compaction_probe import measure

    config = Scene(town=False).with_overrides(agents=agents, weapons=False, cull="gpu", lod_distances=(10.0, 20.0, 30.0)).pipeline_config()
    with CrowdPipeline(gl_context, config) as pipeline:
        pipeline.camera = pipeline.default_camera(16 / 9)
        row = measure(gl_context, pipeline, repeats=1)
    assert row["same_lists"] and row["listed"] >= agents // 2 and row["agents"] == pipeline.rows == agents + 1  # and the survivor
