"""One mechanism for every setting a running crowd takes (crowd.live_settings): each setting of the
schema is live, built with the crowd, or the session's own; a change rebuilds the stages its entry
names and no others; a build that fails keeps the running stages and the old config."""

from __future__ import annotations

import dataclasses

import pytest

from crowd import live_settings
from crowd.gl import Offscreen
from crowd.live_settings import BUILT_WITH, LIVE
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import PipelineConfig, PipelineError
from crowd.scene import Scene
from crowd.settings import SETTINGS, group
from crowd.sim.config import AIConfig

STAGES = ("processor", "renderer", "readback", "weapons", "town")
# A value other than each setting's scene value below, for every live setting that is not the AI's.
CHANGED = {"agents": 12, "seed": 5, "bake_fps": 24.0, "precision": "f16", "interpolation": "slerp", "compression_bound_mm": 0.25,
           "morphs": False, "processor": "fragment", "foot_lock": False, "shadows": False, "cull": "cpu", "culling": False,
           "occlusion": True, "lod_distances": (5.0, 10.0, 20.0), "lod_fade": 0.0, "lod_error_px": 3.0, "impostor_distance": 30.0,
           "impostors": "on", "weapons": False, "readback_latency": 1}


def test_every_setting_is_live_built_with_the_crowd_or_the_sessions():
    named = {n for g in ("scene", "clips", "features", "ai") for n in group(g)}
    assert named == (set(LIVE) - {"time_scale"}) | set(BUILT_WITH)
    assert not set(LIVE) & set(BUILT_WITH)
    assert set(group("ai")) <= set(LIVE)
    for name, live in LIVE.items():
        assert name in SETTINGS
        assert live.field is None or live.field in {f.name for f in dataclasses.fields(PipelineConfig)}
        assert set(live.rebuild) <= set(live_settings.BUILDERS)
    assert set(CHANGED) == set(LIVE) - set(group("ai"))


@pytest.fixture
def pipeline(gl_context):
    # Every stage exists: weapons (read-back and weapon meshes), the town, shadows.
    scene = Scene(agents=10, town=True, survivor=False, ai_path="cpu", impostors="off", occlusion=False, readback_latency=2,
                  ai=AIConfig(half_extent=10.0, armed_share=0.5))
    with Offscreen(gl_context, (96, 54)) as target:
        p = CrowdPipeline(gl_context, scene.pipeline_config())
        try:
            p.frame(target.framebuffer, 1 / 60)
            yield p, target.framebuffer
        finally:
            p.release()


# (The crowd's, the bake's and the atlases' settings rebuild through events of their own: tests/test_session.py,
# test_impostors.py, test_morph_draw.py.)
@pytest.mark.parametrize("name", sorted(set(CHANGED) - {"agents", "seed", "morphs", "impostors", "impostor_distance"}
                                        - set(live_settings.BAKE_SETTINGS)) + ["crossfade"])
def test_a_change_rebuilds_the_stages_its_entry_names_and_no_others(pipeline, name):
    p, fb = pipeline
    assert all(getattr(p, s) is not None for s in STAGES)
    before = {s: getattr(p, s) for s in STAGES}
    value = CHANGED.get(name, 0.3)
    p.set(name, value)
    config = p.config.ai if name in group("ai") else p.config
    assert getattr(config, LIVE[name].field or name) == SETTINGS[name].check(value)
    rebuilt = {s for s in STAGES if getattr(p, s) is not before[s]}
    if name == "weapons":  # (the read-back and the weapon meshes go)
        assert rebuilt == {"readback", "weapons"} and p.readback is None and p.weapons is None
    else:
        assert rebuilt == set(LIVE[name].rebuild), name
    p.frame(fb, 1 / 60)
    p.frame(fb, 1 / 60)


def test_the_same_value_rebuilds_nothing_but_a_seed_starts_a_new_crowd(pipeline):
    p, fb = pipeline
    before = {s: getattr(p, s) for s in STAGES}
    for name in ("shadows", "cull", "processor", "foot_lock", "weapons"):
        p.set(name, getattr(p.config, LIVE[name].field))
    assert all(getattr(p, s) is before[s] for s in STAGES)
    ai = p.ai
    p.set("seed", p.config.seed)
    assert p.ai is not ai


def test_a_build_that_fails_keeps_the_running_stages_and_the_old_config(pipeline, monkeypatch):
    p, fb = pipeline
    before, config = {s: getattr(p, s) for s in STAGES}, p.config
    made = []

    def renderer_then_fail(builders):
        real = builders["renderer"]

        def build(q, parts, spec):
            made.append(real(q, parts, spec))
            return made[-1]
        return {**builders, "renderer": build, "weapons": lambda *a: (_ for _ in ()).throw(PipelineError("no weapons today"))}

    monkeypatch.setattr(live_settings, "BUILDERS", renderer_then_fail(live_settings.BUILDERS))
    with pytest.raises(PipelineError, match="no weapons today"):
        p.set("shadows", False)
    assert p.config is config and all(getattr(p, s) is before[s] for s in STAGES)
    assert len(made) == 1 and not any(made[0]._objects.values())  # the new renderer was built, then released
    p.frame(fb, 1 / 60)


def test_refusals_name_the_setting_in_one_line(pipeline):
    p, _ = pipeline
    with pytest.raises(PipelineError, match="is applied when the crowd is built"):
        p.set("town", False)
    with pytest.raises(PipelineError, match="not a setting a running crowd takes"):
        p.set("frames", 3)
    with pytest.raises(PipelineError) as info:
        p.set("lod_fade", -1.0)
    assert str(info.value) == SETTINGS["lod_fade"].reason(-1.0)
