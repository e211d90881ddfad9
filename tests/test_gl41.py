"""The path without compute shaders (issue 25): the "gl" setting at 4.1 makes the whole frame take the
path a macOS 4.1 core context takes, on a context that has more (llvmpipe's 4.5 here), and that path
draws what the compute path draws."""

from __future__ import annotations

import dataclasses

import moderngl
import numpy as np
import pytest

from crowd.gl import GL_LIMITS, feature_level, has_compute
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import PipelineConfig, PipelineError
from crowd.scene import Scene
from crowd.session import CrowdSession, SessionError
from crowd.smoke import run_headless

SIZE = (320, 180)


def test_the_limit_is_a_ceiling():
    class Ctx:
        version_code = 450

    assert feature_level(Ctx()) == 450 and has_compute(Ctx())
    assert feature_level(Ctx(), GL_LIMITS["4.1"]) == 410 and not has_compute(Ctx(), GL_LIMITS["4.1"])
    Ctx.version_code = 330
    assert feature_level(Ctx(), GL_LIMITS["4.1"]) == 330  # (a ceiling, never a promotion)


def test_the_41_path_uses_no_compute_storage_buffer_or_image_store(compute_context, no_compute_features, tmp_path, monkeypatch):
    """The whole frame at 4.1 (weapons and their read-back ring, shadows, morph targets, impostors baked and
    drawn, the transform-feedback cull) runs with every GL 4.3 entry point refused, and allocates nothing
    for the compute path's state."""
    monkeypatch.setenv("CROWD_CACHE_DIR", str(tmp_path))
    config = PipelineConfig(agents=60, seed=4, gl="4.1", impostors="on", impostor_distance=12.0)
    stats = run_headless(config, 6, SIZE, ctx=compute_context)
    assert stats["gl_features"] == 410 and stats["processor_path"] == "fragment" and stats["cull_path"] == "feedback"
    assert all(stats["gpu_bytes"].get(k, 0) == 0 for k in ("foot_lock", "occlusion")) and stats["gpu_bytes"]["cull"] > 0
    assert {"process", "cull", "draw", "shadow", "impostors", "weapons"} <= set(stats["passes_run"])
    assert stats["nan_count"] == 0 and stats["last_frame"]["instances"] > 0


def test_the_41_path_draws_the_compute_paths_picture(compute_context):
    """The same crowd on both paths, the foot lock off (it runs on the compute path only): the pictures
    agree to a level of rounding, the weapons included (placed from the read-back ring on both)."""
    images = {}
    for gl in ("auto", "4.1"):
        stats = run_headless(PipelineConfig(agents=80, seed=6, gl=gl, foot_lock=False, ai_path="cpu"), 6, SIZE, ctx=compute_context)
        assert stats["gl_features"] == (compute_context.version_code if gl == "auto" else 410)
        images[gl] = stats["_image"].astype(int)
    assert np.max(np.abs(images["auto"] - images["4.1"])) <= 1


def test_the_41_path_refuses_what_needs_compute_in_one_line(compute_context):
    with pytest.raises(Exception, match=r"the compute path needs GL 4.3, this context has \d+, used as GL 4.1 \(--gl\)"):
        CrowdPipeline(compute_context, PipelineConfig(agents=4, gl="4.1", processor_path="compute"))
    with pytest.raises(Exception, match=r"the gpu cull path needs GL 4.3 compute shaders; this context is GL \d+, used as GL 4.1 \(--gl\)"):
        CrowdPipeline(compute_context, PipelineConfig(agents=4, gl="4.1", cull="gpu"))
    with pytest.raises(PipelineError, match="GL feature level"):
        CrowdPipeline(compute_context, PipelineConfig(agents=4, gl="3.0"))


def test_a_running_crowd_keeps_its_gl_level_and_saves_it(compute_context):
    session = CrowdSession(compute_context, dataclasses.replace(Scene(agents=4, shadows=False, town=False), gl="4.1"), SIZE[0] / SIZE[1])
    try:
        with pytest.raises(SessionError, match="applied when the crowd is built"):
            session.set("gl", "auto")
        assert session.to_scene().gl == "4.1" and session.pipeline.processor.path == "fragment"
        with pytest.raises(SessionError, match="used as GL 4.1"):
            session.set("processor", "compute")
    finally:
        session.release()


def test_crowd_bench_fragment_times_both_draws_and_the_floor(gl_context):
    from bench.fragment_probe import measure

    (row,) = measure(gl_context, [64], repeats=1)
    assert row["agents"] == 64 and row["texels"] == 64 * 23
    assert all(row[k] >= 0.0 for k in ("fragment_ms", "locals_ms", "compose_ms", "floor_3_targets_ms", "floor_1_target_ms"))
    assert ("compute_ms" in row) == has_compute(gl_context)


def test_every_shader_the_41_path_compiles_is_valid_for_its_glsl_version(compute_context, tmp_path, monkeypatch):
    """Mesa and NVIDIA accept GLSL that a stricter compiler (Apple's) may not, such as a macro continued over
    lines in a #version 410 shader (line continuation came with 4.20). Every source the 4.1 frame compiles,
    with its defines, weapons, shadows, morphs, fades and impostors on, goes through the Khronos reference
    compiler (glslangValidator, which .ci/run installs; skipped without it)."""
    import shutil
    import subprocess

    validator = shutil.which("glslangValidator")
    if validator is None:
        pytest.skip("glslangValidator not installed (.ci/run installs glslang-tools)")
    monkeypatch.setenv("CROWD_CACHE_DIR", str(tmp_path))
    sources = {}
    compile_program = moderngl.Context.program

    def recorded(self, *args, **kwargs):
        for stage in ("vertex_shader", "geometry_shader", "fragment_shader"):
            if kwargs.get(stage):
                sources[kwargs[stage]] = stage[:4]  # vert, geom, frag: the validator's stage from the extension
        return compile_program(self, *args, **kwargs)

    monkeypatch.setattr(moderngl.Context, "program", recorded)
    run_headless(PipelineConfig(agents=80, seed=3, gl="4.1", impostors="on", impostor_distance=12.0, lod_fade=2.0), 3, SIZE, ctx=compute_context)
    assert len(sources) > 20 and any("EmitStreamVertex" in source for source in sources)
    failed = []
    for k, (source, stage) in enumerate(sources.items()):
        path = tmp_path / f"shader{k}.{stage}"
        path.write_text(source)
        result = subprocess.run([validator, str(path)], capture_output=True, text=True)
        if result.returncode:
            failed.append(f"{source.splitlines()[1][:80]}: {result.stdout.strip().splitlines()[1:3]}")
    assert not failed, failed
