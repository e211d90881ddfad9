"""The panel's actions, without a window: every control goes through CrowdSession, the same object
the window drives, and the scene it saves loads back as the run that saved it."""

from __future__ import annotations

import numpy as np
import pytest

from crowd.sim.config import HIT, AIConfig
from crowd.frame import CLIP, PHASE, WEIGHT
from crowd.scene import CharacterEntry, Scene, load_scene
from crowd.session import CrowdSession, SessionError
from crowd.gl import Offscreen

SIZE = (192, 108)
DT = 1.0 / 60.0


@pytest.fixture
def session(gl_context):
    made = []

    def make(**scene):
        # The built-in zombie alone and no survivor, on the numpy AI (tests/test_cast.py has the mixed crowd's, test_survivor.py the
        # game's, test_gpu_pipeline.py the session on the GPU AI).
        one = {"characters": (CharacterEntry(),), "survivor": False}
        s = CrowdSession(gl_context, Scene(**{"agents": 30, "shadows": False, "ai": AIConfig(half_extent=8.0), "ai_path": "cpu", **one, **scene}), SIZE[0] / SIZE[1])
        target = Offscreen(gl_context, SIZE)
        fb = target.framebuffer
        made.append((s, target))
        return s, fb

    yield make
    for s, target in made:
        s.release()
        target.release()


def test_pause_single_step_and_time_scale(session):
    s, fb = session()
    s.frame(fb, DT)
    t0 = s.pipeline.ai.time
    s.set_paused(True)
    for _ in range(3):
        s.frame(fb, DT)
    assert s.pipeline.ai.time == t0
    s.step_once()
    s.frame(fb, DT)
    s.frame(fb, DT)
    assert s.pipeline.ai.time == pytest.approx(t0 + 1 / 60)
    s.set_paused(False)
    s.set("time_scale", 2.0)
    s.frame(fb, DT)
    assert s.pipeline.ai.time == pytest.approx(t0 + 3 / 60)
    for bad in (-1.0, 11.0, float("nan")):
        with pytest.raises(SessionError, match="time scale"):
            s.set("time_scale", bad)
    with pytest.raises(SessionError, match="frame time"):
        s.frame(fb, float("inf"))


def test_agent_count_live_from_0_to_10000_and_back(session):
    s, fb = session()
    s.selected = 25
    for n in (0, 10_000, 0, 200):
        s.set("agents", n)
        s.frame(fb, DT)
        assert s.pipeline.agents == n and s.pipeline.processor.nan_rows() == 0
    assert s.selected == -1  # agent 25 went away with the count at 0
    with pytest.raises(SessionError, match="agent count"):
        s.set("agents", -1)


def test_play_a_clip_on_all_then_give_control_back(session):
    s, fb = session()
    s.frame(fb, DT)
    s.set_clip_speed("attack", 2.0)
    s.play("attack", selected_only=False)
    for _ in range(6):
        s.frame(fb, DT)
    layers = s.pipeline.layers
    attack = s.clip_names().index("attack")
    assert np.all(layers[:, 0, CLIP] == attack) and np.all(layers[:, 0, WEIGHT] == 1.0) and np.all(layers[:, 1:, WEIGHT] == 0.0)
    duration = s.pipeline.bake.clips[attack].duration
    assert layers[0, 0, PHASE] == pytest.approx(6 * DT * 2.0 / duration, rel=1e-4)  # time x speed / duration
    s.play(None)
    s.frame(fb, DT)
    assert set(s.pipeline.layers[:, 0, CLIP].tolist()) == {s.clip_names().index("idle")}  # the AI's idle layer again
    with pytest.raises(SessionError, match="no agent selected"):
        s.play("attack")
    with pytest.raises(SessionError, match="was not baked"):
        s.play("moonwalk", selected_only=False)


def test_held_weight_on_the_selected_agent_only(session):
    s, fb = session()
    s.selected = 4
    s.set_weight(2, 0.75, selected_only=True)
    s.frame(fb, DT)
    assert s.pipeline.layers[4, 2, WEIGHT] == 0.75
    assert s.inspect()["layers"][2]["weight"] == 0.75
    s.set_weight(2, None)
    with pytest.raises(SessionError, match="weight"):
        s.set_weight(1, float("nan"))
    with pytest.raises(SessionError, match="layer"):
        s.set_weight(4, 1.0)


def test_clip_speed_moves_the_walk_faster_and_loop_reaches_the_gpu(session):
    s, fb = session()
    walk = s.pipeline.roles["walk"]
    base = s.pipeline.motion.walk_speed
    s.set_clip_speed(walk, 1.5)
    assert s.pipeline.motion.walk_speed == pytest.approx(1.5 * base)  # feet stay planted
    assert s.pipeline.ai.walk_top.max() <= 1.5 * base * s.pipeline.ai.config.speed_max + 1e-9
    with pytest.raises(SessionError, match="playback speed"):
        s.set_clip_speed(walk, 0.0)
    s.set_clip_loop("attack", True)
    table = np.frombuffer(s.pipeline.processor.parts[0].textures["u_clips"].read(), np.float32).reshape(-1, 4)
    assert table[s.clip_names().index("attack"), 3] == 1.0
    s.frame(fb, DT)


def test_rebake_and_features_live(session):
    s, fb = session()
    s.frame(fb, DT)
    old_processor = s.pipeline.processor
    s.rebake(30.0, "f16")
    assert s.pipeline.bake.fps == 30.0 and s.pipeline.bake.precision == "f16" and old_processor.planes == ()
    s.set("shadows", True)
    s.set("weapons", False)
    s.set("lod_distances", (5.0, 10.0, 20.0))
    s.set("culling", False)
    for _ in range(3):
        s.frame(fb, DT)
    bytes_ = s.pipeline.gpu_bytes()
    assert bytes_["shadow_map"] > 0 and "readback" not in bytes_ and s.pipeline.processor.history == 1
    assert s.pipeline.processor.nan_rows() == 0
    s.set("weapons", True)
    s.set("readback_latency", 3)
    for _ in range(5):
        s.frame(fb, DT)
    assert s.pipeline.weapons.last["weapons"] > 0 and s.pipeline.weapon_error_mm() <= 0.1
    with pytest.raises(SessionError, match="bake rate"):
        s.rebake(0.0, "f32")
    with pytest.raises(SessionError, match="interpolation must be one of"):
        s.rebake(30.0, "f32", "slerp")


def test_a_rebake_runs_on_its_thread_while_frames_go_on(session):
    """The panel's re-bake (issue 22, point 6): the bake runs on a thread and says how far it has got,
    frames go on with the old bake meanwhile, a second re-bake is refused until it is done, and polling
    hands the new bake to the pipeline on this thread."""
    import time

    s, fb = session()
    s.frame(fb, DT)
    old = s.pipeline.bake
    s.start_rebake(30, "compressed", bound_mm=0.5)
    lines = set()
    with pytest.raises(SessionError, match="under way"):
        s.rebake(20, "f32")
    with pytest.raises(SessionError, match="under way"):
        s.start_rebake(20, "f32")
    deadline = time.monotonic() + 120
    while s.rebake_progress is not None and time.monotonic() < deadline:
        lines.add(s.rebake_progress)
        s.frame(fb, DT)  # the old bake plays on
        assert s.poll_rebake() is None
    assert s.rebake_progress is None and s.pipeline.bake is not old and s.pipeline.bake.precision == "compressed"
    assert any(line.startswith("re-baking: ") for line in lines)
    s.frame(fb, DT)
    assert s.pipeline.processor.nan_rows() == 0
    with pytest.raises(SessionError):  # checked before a thread starts
        s.start_rebake(0.0, "f32")
    assert s.rebake_progress is None


def test_rebake_interpolation_and_measured_error(session):
    """The panel's bake controls: every interpolation and the source rate re-bake live, and the error
    measured on the GPU tells them apart (dq_lerp blends the hips as a screw: centimetres)."""
    s, fb = session(agents=20)
    s.frame(fb, DT)
    default = s.measure_error(per_clip=6, blends=60)
    assert default["max_error_mm"] < 1.0 and default["poses"] == 6 * len(s.pipeline.bake.clips) + 60
    s.rebake("source", "f32", "dq_lerp")
    assert s.bake_error is None and s.pipeline.bake.fps == "source" and s.pipeline.processor.interpolation == "dq_lerp"
    s.frame(fb, DT)
    assert s.measure_error(per_clip=6, blends=60)["max_error_mm"] > 10.0
    s.rebake(15, "f16", "qt_cubic")
    s.frame(fb, DT)
    assert s.to_scene().interpolation == "qt_cubic" and s.to_scene().bake_fps == 15.0
    with pytest.raises(SessionError, match="LOD"):
        s.set("lod_distances", (10.0, 5.0, 20.0))
    with pytest.raises(SessionError, match="latency"):
        s.set("readback_latency", 0)


def test_pick_an_agent_move_the_player_and_strike(session):
    s, fb = session()
    s.frame(fb, DT)
    ai = s.pipeline.ai
    chest = np.stack([ai.x, np.full(ai.n, 1.2), ai.z], axis=1)
    pixels = s.pipeline.project(chest, SIZE)
    # The agent nearest the camera, so nobody stands in front of it.
    a = int(np.argmin(np.linalg.norm(chest - s.pipeline.camera.eye, axis=1)))
    assert s.pick(*pixels[a], SIZE) == a and s.selected == a
    assert s.pick(SIZE[0] / 2, 1.0, SIZE) == -1 and s.selected == -1  # the sky
    ground = s.ground_point(*pixels[a], SIZE)
    assert ground is not None
    s.move_player((ai.x[a] + 0.5, ai.z[a]))
    assert s.strike() == a and ai.state[a] == HIT
    with pytest.raises(SessionError, match="ground point"):
        s.move_player((float("nan"), 0.0))


def test_saved_scene_loads_back_as_the_run_that_saved_it(session, tmp_path):
    s, fb = session(agents=12)
    s.set("crossfade", 0.4)
    s.set_clip_speed(s.pipeline.roles["run"], 1.25)
    s.set_clip_loop("hit", True)
    s.set("agents", 17)
    s.rebake(20.0, "f32")
    s.frame(fb, DT)
    path = tmp_path / "tweaked.toml"
    s.save(path)
    loaded = load_scene(path)
    assert loaded == s.to_scene()
    assert loaded.agents == 17 and loaded.ai.crossfade == 0.4 and loaded.bake_fps == 20.0
    assert loaded.clip_speed == {s.pipeline.roles["run"]: 1.25} and loaded.clip_loop == {"hit": True}
    again = CrowdSession(s.ctx, loaded, SIZE[0] / SIZE[1])
    try:
        assert again.pipeline.clip_speed == s.pipeline.clip_speed
        assert again.pipeline.bake.clips[again.clip_names().index("hit")].loop
        assert np.allclose(again.pipeline.camera.eye, s.pipeline.camera.eye)
    finally:
        again.release()


def test_inspector(session):
    s, fb = session()
    s.frame(fb, DT)
    s.selected = 3
    info = s.inspect()
    assert info["agent"] == 3 and info["state"] in ("wander", "chase", "attack", "hit", "dying", "dead")
    assert len(info["layers"]) == 4 and {l["clip"] for l in info["layers"][:3]} == {"idle", "shamble", "run"}
    assert info["weapon"] in (None, "pipe", "axe")
    assert s.inspect(10_000) is None


def test_panel_actions_go_through_the_session_and_report_refusals(session, tmp_path):
    from app.panel import Panel

    s, fb = session()
    panel = Panel(s, tmp_path / "panel.toml")
    assert panel.apply("clip_speed", "idle", 0.5) and s.pipeline.clip_speed == {"idle": 0.5}
    assert not panel.apply("agents", -4) and "agent count" in panel.status and s.pipeline.agents == 30
    assert panel.apply("weight", 1, 0.3) and panel.status == ""
    assert panel.apply("cull", "cpu") and s.pipeline.renderer.cull_path == "cpu"
    assert not panel.apply("cull", "sideways") and "cull" in panel.status and s.pipeline.renderer.cull_path == "cpu"
    assert panel.apply("save") and "saved" in panel.status
    assert load_scene(tmp_path / "panel.toml").clip_speed == {"idle": 0.5}
    assert load_scene(tmp_path / "panel.toml").cull == "cpu"
    assert panel.apply("save") and "panel.toml.bak" in panel.status


def test_held_morph_weights_from_the_panel(session):
    """A target's weight held on every zombie, then on the selected one only; bad values refused in one
    line; the morphs switched off and on live, the held weights kept for the new processor."""
    s, fb = session()
    s.frame(fb, DT)
    assert s.morph_character() == 0  # the zombie's clips key its snarl
    s.set_morph_weight("belly_swell", 0.8)
    s.frame(fb, DT)
    pairs = s.pipeline.processor.read_morph_pairs()
    belly = list(s.pipeline.character.morphs).index("belly_swell")
    assert np.all(np.any((pairs[..., 0] == belly) & np.isclose(pairs[..., 1], 0.8), axis=1))
    for bad, words in ((float("nan"), "morph weight"), (1.5, "morph weight"), (-0.2, "morph weight")):
        with pytest.raises(SessionError, match=words) as info:
            s.set_morph_weight("belly_swell", bad)
        assert "\n" not in str(info.value)
    with pytest.raises(SessionError, match="no morph target 'nose'"):
        s.set_morph_weight("nose", 0.5)
    with pytest.raises(SessionError, match="no agent selected"):
        s.set_morph_weight("gaunt", 0.5, selected_only=True)
    s.selected = 4
    s.set_morph_weight("gaunt", 1.0, selected_only=True)  # the character's held targets now apply to agent 4 alone
    s.frame(fb, DT)
    pairs = s.pipeline.processor.read_morph_pairs()
    gaunt = list(s.pipeline.character.morphs).index("gaunt")
    has = np.any((pairs[..., 0] == gaunt) & np.isclose(pairs[..., 1], 1.0), axis=1)
    assert has[4] and has.sum() == 1
    assert s.held_morphs() == {"belly_swell": pytest.approx(0.8), "gaunt": 1.0}
    s.set("morphs", False)
    s.frame(fb, DT)
    assert s.morph_character() is None and s.pipeline.processor.gpu_bytes()["morphs"] == 0
    with pytest.raises(SessionError, match="no character moves morph targets"):
        s.set_morph_weight("gaunt", 0.5)
    s.set("morphs", True)
    s.frame(fb, DT)
    assert s.pipeline.processor.read_morph_pairs()[4, 0, 0] in (gaunt, belly)  # held again, on the new processor
    s.set_morph_weight("gaunt", None)
    s.set_morph_weight("belly_swell", None)
    assert s.held_morphs() == {}
