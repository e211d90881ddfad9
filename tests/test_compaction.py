"""crowd-bench compaction (bench/compaction_probe.py): the GPU cull's compacted lists, checked against the
numpy cull's, and what they cost an agent."""

from __future__ import annotations

import pytest

from crowd.gl import has_compute


def test_the_benchmark_checks_its_lists_and_counts_their_bytes(gl_context):
    if not has_compute(gl_context):
        pytest.skip("the GPU cull needs GL 4.3")
    from bench.compaction_probe import measure
    from crowd.draw.render import CrowdRenderer
    from crowd.pipeline import CrowdPipeline
    from crowd.scene import Scene

    with CrowdPipeline(gl_context, Scene(town=False).with_overrides(agents=3000, weapons=False, cull="gpu").pipeline_config()) as pipeline:
        pipeline.camera = pipeline.overview_camera(16 / 9)
        r = pipeline.renderer
        with CrowdRenderer(gl_context, r.cast, lod_distances=r.lod_distances, shadows=r.shadows, cull_path="cpu", morphs=r.morphs,
                           lod_fade=r.lod_fade) as cpu:
            row = measure(gl_context, pipeline, cpu, repeats=2)
    assert row["entries"] > 1000 and row["entries_unlike_the_numpy_cull"] <= row["entries"] // 1000  # agents at a boundary
    assert 0 < row["list_bytes_per_agent"] <= 64 and row["ms"] >= 0  # (llvmpipe's timer may read 0)
