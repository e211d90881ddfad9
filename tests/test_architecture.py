"""The floor plan (docs/ARCHITECTURE.md): the import rules, the one settings schema, and stages that
release their GL objects on every path."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
import tomllib

import numpy as np
import pytest

from conftest import ROOT, gl_census
from crowd.frame import ForcedClip, LayerOverrides
from crowd.gl import Offscreen
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import PipelineConfig
from crowd.scene import Scene, SceneError, load_scene
from crowd.session import CrowdSession, SessionError
from crowd.settings import SCENE_GROUPS, SETTINGS, SettingError, group, parse
from crowd.sim.config import AIConfig
from crowd.smoke import FIXED_DT

SIZE = (64, 36)


# -- the import rules


def test_import_rules_hold():
    """lint-imports checks every contract in pyproject.toml: layers in data-flow order, no runtime
    import of bench/ or app/, a GL-free AI, an importer without the bake or reference, no circles."""
    out = subprocess.run([sys.executable, "-c", "from importlinter.cli import lint_imports_command; lint_imports_command()"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    assert f"Contracts: {len(contracts)} kept, 0 broken." in out.stdout


def test_import_rules_catch_a_broken_rule(tmp_path):
    """The same contracts, on a copy of the code in which the AI imports the renderer: must fail."""
    import shutil

    for name in ("crowd", "app", "bench"):
        shutil.copytree(ROOT / name, tmp_path / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    ai = tmp_path / "crowd" / "sim" / "ai.py"
    ai.write_text(ai.read_text().replace("from ..frame import", "from ..draw.render import CrowdRenderer  # noqa\nfrom ..frame import", 1))
    out = subprocess.run([sys.executable, "-c", "import sys; sys.path.insert(0, '.'); "
                          "from importlinter.cli import lint_imports_command; lint_imports_command()"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert out.returncode != 0
    assert "The numpy AI is plain numpy" in out.stdout and "BROKEN" in out.stdout


# -- one settings schema


def test_every_setting_declares_type_bounds_default_and_help():
    for s in SETTINGS.values():
        assert s.help and s.kind in ("int", "float", "bool", "choice", "rate", "scale", "ascending", "size"), s.name
        assert s.check(s.default) == s.default, s.name  # the default passes its own check
        if s.slider is not None:
            lo, hi = s.slider
            assert s.low <= lo < hi and (hi <= s.high), s.name  # the panel's widget stays inside the bounds
    assert [f.name for f in dataclasses.fields(AIConfig)] == list(group("ai"))  # AIConfig is the ai group
    assert AIConfig() == AIConfig(**{name: s.default for name, s in group("ai").items()})


def _out_of_range(s):
    """A value each setting must refuse: past a bound, or of the wrong type where it has no bound."""
    if s.kind == "bool":
        return "yes"
    if s.kind == "choice":
        return "nonsense"
    if s.kind == "rate":
        return s.high + 1
    if s.kind == "ascending":
        return (5.0, 2.0) + tuple(s.default[2:])  # out of order
    if s.high < math.inf:
        return int(s.high) + 1 if s.kind == "int" else s.high + 1.0
    if s.low > -math.inf:
        return int(s.low) - 1 if s.kind == "int" else s.low - 1.0
    return float("nan")


def _cli_text(value) -> str:
    return ",".join(str(v) for v in value) if isinstance(value, tuple) else str(value)


def _reason(message: str, source: str) -> str:
    assert message.startswith(source + ": "), (message, source)
    return message[len(source) + 2:]


@pytest.fixture(scope="module")
def running(gl_context):
    session = CrowdSession(gl_context, Scene(agents=4, shadows=False), SIZE[0] / SIZE[1])
    yield session
    session.release()


@pytest.mark.parametrize("name", [n for t in SCENE_GROUPS for n in group(t)])
def test_cli_scene_file_and_session_refuse_the_same_value_with_the_same_line(tmp_path, running, name):
    s = SETTINGS[name]
    bad = _out_of_range(s)
    expected = s.reason(bad)
    assert "\n" not in expected
    # The scene file.
    path = tmp_path / "bad.toml"
    toml_value = list(bad) if isinstance(bad, tuple) else bad
    if isinstance(toml_value, float) and math.isnan(toml_value):
        text = f"[{s.group}]\n{name} = nan\n"
    else:
        text = f"[{s.group}]\n{name} = {toml_value!r}\n".replace("'", '"').replace("(", "[").replace(")", "]")
    path.write_text(text)
    with pytest.raises(SceneError) as from_file:
        load_scene(path)
    assert _reason(str(from_file.value), f"{path}: {s.group}.{name}") == expected
    # The command line: the flag's text as the setting's type, checked by the scene (as crowd-demo does).
    with pytest.raises(SceneError) as from_cli:
        Scene().with_overrides(**{name: s.from_text(_cli_text(bad))})
    assert _reason(str(from_cli.value), s.flag) == expected
    # The running session (the panel's path).
    before = running.to_scene()
    with pytest.raises(SessionError) as from_session:
        running.set(name, bad)
    assert str(from_session.value) == expected
    assert running.to_scene() == before  # refused: nothing changed


def test_the_demo_refuses_a_bad_flag_in_one_line():
    out = subprocess.run([sys.executable, "-m", "app.demo", "--headless", "--readback-latency", "7", "--size", "64x36"],
                         capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.strip() == "crowd-demo: --readback-latency: " + SETTINGS["readback_latency"].reason(7)


def test_session_only_and_run_settings_are_checked_by_the_schema_too(running):
    with pytest.raises(SessionError, match=SETTINGS["time_scale"].reason(11.0)):
        running.set("time_scale", 11.0)
    with pytest.raises(SessionError) as info:
        running.set_clip_speed(running.clip_names()[0], 50.0)
    assert str(info.value) == SETTINGS["clip_speed"].reason(50.0)
    with pytest.raises(SessionError) as info:
        running.set_weight(1, 2000.0)
    assert str(info.value) == SETTINGS["layer_weight"].reason(2000.0)
    with pytest.raises(SettingError, match="frames"):
        parse("frames", "0")
    assert parse("size", "320x180") == (320, 180)


# -- layer overrides are an input of the frame


def test_layer_overrides_are_an_input_of_the_frame(gl_context):
    with CrowdPipeline(gl_context, PipelineConfig(agents=3, shadows=False, weapons=False)) as p, Offscreen(gl_context, SIZE) as target:
        p.frame(target.framebuffer, FIXED_DT)
        plain = p.layers.copy()
        attack = p.bake.clip_index(p.roles["attack"])
        overrides = LayerOverrides(ForcedClip(attack, p.ai.time, np.array([1])), {2: (0.5, None)})
        p.frame(target.framebuffer, FIXED_DT, overrides)
        assert p.layers[1, 0, 0] == attack and p.layers[1, 0, 2] == 1.0 and np.all(p.layers[1, 1:, 2][:1] == 0.0)
        assert np.all(p.layers[:, 2, 2] == 0.5) and p.layers[0, 0, 0] == plain[0, 0, 0]
        with pytest.raises(Exception, match="forced clip"):
            p.frame(target.framebuffer, FIXED_DT, LayerOverrides(ForcedClip(99, 0.0)))


# -- GL objects are released on every path


def test_an_exception_inside_a_frame_leaves_no_gl_object(gl_context, monkeypatch):
    before = gl_census()
    config = PipelineConfig(agents=40, seed=2, readback_latency=2)
    with pytest.raises(RuntimeError, match="injected"):
        with Offscreen(gl_context, SIZE) as target, CrowdPipeline(gl_context, config) as p:
            for _ in range(3):
                p.frame(target.framebuffer, FIXED_DT)
            assert p.readback is not None and p.weapons is not None  # every stage exists
            assert gl_census() != before

            def broken(*args, **kwargs):
                raise RuntimeError("injected failure in the middle of a frame")

            monkeypatch.setattr(p.weapons, "attach", broken)
            p.frame(target.framebuffer, FIXED_DT)
    assert gl_census() == before


def test_a_stage_that_fails_half_built_releases_what_it_made(gl_context, monkeypatch):
    """The processor is built, then the renderer fails after some of its meshes are on the GPU."""
    import crowd.draw.render as render

    before = gl_census()
    real, calls = render.pack_vertices, []

    def fails_on_the_fourth_mesh(mesh):
        calls.append(mesh)
        if len(calls) == 4:
            raise RuntimeError("injected failure while building the renderer")
        return real(mesh)

    monkeypatch.setattr(render, "pack_vertices", fails_on_the_fourth_mesh)
    with pytest.raises(RuntimeError, match="injected"):
        CrowdPipeline(gl_context, PipelineConfig(agents=10))
    assert len(calls) == 4 and gl_census() == before


def test_resizing_from_0_to_a_crowd_and_back_leaks_nothing(gl_context):
    with Offscreen(gl_context, SIZE) as target, CrowdPipeline(gl_context, PipelineConfig(agents=0, shadows=False)) as p:
        p.frame(target.framebuffer, FIXED_DT)
        start = gl_census()
        for n in (5000, 0, 300, 0):
            p.set("agents", n)
            p.frame(target.framebuffer, FIXED_DT)
        p.set("weapons", False)
        p.set("weapons", True)
        p.set("shadows", True)
        p.set("shadows", False)
        p.frame(target.framebuffer, FIXED_DT)
        assert {k: len(v) for k, v in gl_census().items()} == {k: len(v) for k, v in start.items()}


# -- regressions found in review


@pytest.mark.parametrize("change", ["shadows", "rebake", "latency", "processor"])
def test_stages_follow_what_exists_after_the_armed_share_drops_to_zero(gl_context, change):
    """Set at run time, armed_share 0 leaves the weapon stages in place (nobody to gather). A later
    rebuild must size the palette ring and the weapons for the stages that exist, not for the settings."""
    session = CrowdSession(gl_context, Scene(agents=40), scripted_player=True)
    try:
        with Offscreen(gl_context, SIZE) as target:
            for _ in range(4):
                session.frame(target.framebuffer, FIXED_DT)
            session.set("armed_share", 0.0)
            {"shadows": lambda: session.set("shadows", False), "rebake": lambda: session.rebake(20, "f32"),
             "latency": lambda: session.set("readback_latency", 3), "processor": lambda: session.set("processor", "fragment")}[change]()
            p = session.pipeline
            assert p.readback is not None and p.weapons is not None and p.processor.history == p.latency + 1
            for _ in range(5):
                session.frame(target.framebuffer, FIXED_DT)
    finally:
        session.release()


def test_numbers_past_float_range_and_past_storage_are_refused_in_one_line(tmp_path):
    for table, key, value in (("clips", "bake_fps", "1" + "0" * 320), ("ai", "notice_radius", "1" + "0" * 320),
                              ("ai", "health", "40000"), ("clips.speed", "shamble", "1" + "0" * 320)):
        path = tmp_path / "huge.toml"
        path.write_text(f"[{table}]\n{key} = {value}\n")
        with pytest.raises(SceneError) as info:
            load_scene(path)
        message = str(info.value)
        assert "\n" not in message and len(message) < 300 and f"{key}" in message
    with pytest.raises(SceneError, match="AI setting health must be a whole number from 1 to 1000"):
        Scene().with_overrides(health=SETTINGS["health"].from_text("40000"))
    out = subprocess.run([sys.executable, "-m", "app.demo", "--headless", "--notice-radius", "1" + "0" * 320, "--size", "64x36"],
                         capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 2 and "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1


def test_session_stores_settings_as_the_schema_types_so_the_scene_saves(gl_context, tmp_path):
    session = CrowdSession(gl_context, Scene(agents=3, shadows=False))
    try:
        session.set("notice_radius", np.float32(20.0))
        session.set("health", np.int64(5))
        assert type(session.ai_setting("notice_radius")) is float and type(session.ai_setting("health")) is int
        session.save(tmp_path / "saved.toml")
        assert load_scene(tmp_path / "saved.toml").ai.notice_radius == 20.0
        with pytest.raises(SessionError, match="layer must be a whole number"):
            session.set_weight(1.5, 0.5)
    finally:
        session.release()


def test_the_demo_takes_no_abbreviated_flags():
    """argparse's prefix matching made --se and --re mean one of several flags; a flag is spelled out."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-m", "app.demo", "--headless", "--se", "3"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "unrecognized arguments: --se 3" in out.stderr and "Traceback" not in out.stderr
