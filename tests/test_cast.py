"""A crowd of several characters (issue 22, point 1): the cast's counts and moves, each character's bake
processed into its own block of one palette on both processor paths, the cull's lists per character on
both cull paths, a mixed scene of three characters drawn at their shares, the AI's per-character
motion, and scene files and flags that name a cast."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import gltf_factory
from conftest import ROOT
from crowd.anim.processor import AnimationProcessor
from crowd.anim.palette_reference import reference_palette
from crowd.anim.roles import bake_roles, match_roles
from crowd.asset.gltf import load_character
from crowd.frame import CLIP, MASK, PHASE, WEIGHT, FrameError, Instances, cast_counts, cast_firsts, cast_moves, move_agents
from crowd.gl import Offscreen, has_compute
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import CharacterSpec, PipelineConfig
from crowd.scene import Scene, SceneError, load_scene, save_scene
from crowd.sim.ai import CrowdAI
from crowd.sim.config import AIConfig
from crowd.sim.motion import motion_for

PATHS = ("compute", "fragment")


@pytest.fixture(scope="module")
def chain_file(tmp_path_factory):
    """A third character unlike the other two: 3 joints, one clip, no props (tests/gltf_factory)."""
    return gltf_factory.make_gltf(tmp_path_factory.mktemp("cast"), "chain.gltf")


@pytest.fixture(scope="module")
def cast(chain_file):
    """(character, roles, bake) for the zombie, the brute and the chain."""
    out = []
    for model in (None, "brute", chain_file):
        character = load_character(model)
        roles, _ = match_roles(character.clips)
        out.append((character, roles, bake_roles(character, roles)))
    return out


# -- the counts and moves


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2_000_000), st.lists(st.floats(1e-3, 1e3), min_size=1, max_size=16))
def test_counts_sum_to_the_crowd_and_stay_within_one_agent_of_each_share(agents, shares):
    counts = cast_counts(agents, shares)
    exact = agents * np.asarray(shares) / np.sum(shares)
    assert sum(counts) == agents and len(counts) == len(shares)
    assert np.all(np.abs(np.asarray(counts) - exact) < 1.0 + 1e-9)
    assert counts == cast_counts(agents, shares)  # one rule, the same answer


@pytest.mark.parametrize("shares", [[], [0.0], [-1.0, 1.0], [float("nan")], [float("inf")], [1.0] * 257])
def test_bad_shares_are_refused_in_one_line(shares):
    with pytest.raises(FrameError) as info:
        cast_counts(10, shares)
    assert "\n" not in str(info.value)


def test_a_resize_keeps_each_characters_first_agents():
    old, new = cast_counts(100, [3, 1]), cast_counts(40, [3, 1])
    moves = cast_moves(old, new)
    assert moves == [(0, 0, 30), (75, 30, 10)]
    ids = np.arange(100)
    moved = move_agents(ids, moves, 40, fill=-1)
    assert moved[:30].tolist() == list(range(30)) and moved[30:].tolist() == list(range(75, 85))
    grown = move_agents(moved, cast_moves(new, cast_counts(200, [3, 1])), 200, fill=-1)
    first = cast_firsts(cast_counts(200, [3, 1]))
    assert grown[first[1]:first[1] + 10].tolist() == list(range(75, 85)) and np.count_nonzero(grown >= 0) == 40


# -- the processor: one dispatch (or draw) per character, each into its own block


def _cast_layers(bakes, counts, rng):
    """Random layers for each character's block, from its own bake's clips."""
    parts = []
    for bake, n in zip(bakes, counts):
        layers = np.zeros((n, 4, 4), np.float32)
        layers[..., CLIP] = rng.integers(0, len(bake.clips), (n, 4))
        layers[..., PHASE] = rng.uniform(0, 1, (n, 4))
        layers[..., WEIGHT] = rng.uniform(0, 1, (n, 4))
        layers[..., MASK] = -1
        parts.append(layers)
    return np.concatenate(parts)


@pytest.mark.parametrize("path", PATHS)
def test_each_character_is_processed_as_its_own_bake_says(gl_context, cast, path):
    if path == "compute" and not has_compute(gl_context):
        pytest.skip("no GL 4.3 here")
    bakes = [b for _, _, b in cast]
    counts = (70, 31, 5)
    rng = np.random.default_rng(3)
    layers = _cast_layers(bakes, counts, rng)
    with AnimationProcessor(gl_context, bakes, 4, path=path) as proc:
        proc.resize(counts)
        proc.process(layers)
        palette = proc.read_palette()
        first = cast_firsts(counts)
        for k, bake in enumerate(bakes):
            block = slice(first[k], first[k + 1])
            ref = reference_palette(bake, layers[block], interpolation=proc.interpolation)
            jc = bake.joint_count
            assert np.allclose(palette[block, :jc], ref, atol=2e-5), k
            assert not palette[block, jc:].any()  # nothing past its own joints
        assert proc.nan_rows() == 0
        # The layout: every character's rows are its own, each agent's texel unique.
        x, y = proc.layout.texel(np.arange(sum(counts)), 0)
        assert len(set(zip(x.tolist(), y.tolist()))) == sum(counts)
        assert proc.layout.agents_at(x, y).tolist() == list(range(sum(counts)))


def test_clips_of_another_character_are_refused_for_its_block(gl_context, cast):
    bakes = [b for _, _, b in cast]
    with AnimationProcessor(gl_context, bakes, 4, path="fragment") as proc:
        proc.resize((4, 4, 4))
        layers = _cast_layers(bakes, (4, 4, 4), np.random.default_rng(1))
        layers[9, 0, CLIP] = len(bakes[2].clips)  # the chain has one clip
        with pytest.raises(FrameError, match="character 2"):
            proc.upload(layers)


def test_a_resize_keeps_each_characters_palettes(gl_context, cast):
    bakes = [b for _, _, b in cast]
    path = "compute" if has_compute(gl_context) else "fragment"
    rng = np.random.default_rng(5)
    with AnimationProcessor(gl_context, bakes, 4, path=path, history=3) as proc:
        old = (400, 120, 9)
        proc.resize(old)
        proc.process(_cast_layers(bakes, old, rng))
        before = proc.read_palette()
        new = (10, 260, 2)
        proc.resize(new)  # other rows: new planes, the kept agents' rows copied across
        after = proc.read_palette()
        for (was, now, kept), bake in zip(cast_moves(old, new), bakes):
            assert np.array_equal(after[now:now + kept, :bake.joint_count], before[was:was + kept, :bake.joint_count])


# -- the renderer: the cull's lists per character, both paths


def _mixed_instances(counts, rng, spread=30.0):
    n = sum(counts)
    position = np.column_stack([rng.uniform(-spread, spread, n), np.zeros(n), rng.uniform(-spread, spread, n)])
    heads = np.concatenate([rng.integers(0, 2, counts[0]), rng.integers(0, 2, counts[1]), np.zeros(counts[2], int)])
    return Instances(position, rng.uniform(-3, 3, n).astype(np.float32), rng.uniform(0.9, 1.1, n).astype(np.float32),
                     np.full((n, 4), 255, np.uint8), {"head": heads}, tuple(counts))


def test_gpu_and_cpu_culls_put_each_character_in_its_own_draws(gl_context, cast):
    if not has_compute(gl_context):
        pytest.skip("no GL 4.3 here")
    from crowd.draw.cull_lists import entry_agents
    from crowd.draw.render import CrowdRenderer
    from crowd.frame import Camera

    characters = [c for c, _, _ in cast]
    counts = (300, 100, 40)
    rng = np.random.default_rng(2)
    instances = _mixed_instances(counts, rng)
    camera = Camera(eye=np.array([0.0, 20.0, 45.0]), target=np.zeros(3), aspect=16 / 9)
    drawn = {}
    for path in ("cpu", "gpu", "feedback"):
        with CrowdRenderer(gl_context, characters, lod_distances=(14, 40, 90), shadows=True, cull_path=path) as r:
            r.prepare(camera, instances)
            lists = []
            if path != "cpu":
                r.refresh_counts(wait=True)
            for d, draw in enumerate(r.draws):
                if path == "feedback":  # (a list of its own per (character, LOD, choice), as long as its character's agents)
                    assert r.feedback.list_buffer(d).size == counts[draw.character] * 4
                agents = entry_agents(r.listed(d))[0]
                assert len(agents) == draw.count
                block = cast_firsts(counts)[draw.character:draw.character + 2]
                assert np.all((agents >= block[0]) & (agents < block[1])), (path, draw.piece)  # only its own character's agents
                lists.append((draw.character, draw.piece, draw.lod, frozenset(agents.tolist())))
            drawn[path] = (lists, dict(r.last))
    for path in ("gpu", "feedback"):
        assert drawn["cpu"][0] == drawn[path][0]
        assert drawn["cpu"][1]["cast_visible"] == drawn[path][1]["cast_visible"] and sum(drawn["cpu"][1]["cast_visible"]) > 0
        assert drawn["cpu"][1]["lod_counts"] == drawn[path][1]["lod_counts"]


# -- a mixed scene of three characters


def _tinted(pipeline, colors):
    """Every agent of character k tinted colors[k] from now on (the AI keeps each agent's tint)."""
    first = cast_firsts(pipeline.ai.cast)
    for k, color in enumerate(colors):
        pipeline.ai.tint[first[k]:first[k + 1], :3] = color
    if pipeline.gpu_crowd is not None:  # a crowd on the GPU takes the numpy AI's state again (before its first frame: the same)
        pipeline.gpu_crowd.load(pipeline.ai)


@pytest.mark.parametrize("cull", ["gpu", "cpu", "feedback"])
def test_a_mixed_scene_of_three_draws_each_at_its_share(gl_context, chain_file, cull):
    """Zombies, brutes and the chain at 5 : 3 : 2: all three are drawn, each at its share within 2 % of
    the crowd, in its own colour, with finite palettes; zombies and brutes hold their own weapons."""
    if cull == "gpu" and not has_compute(gl_context):
        pytest.skip("no GL 4.3 here")
    cast = (CharacterSpec("zombie", 5.0), CharacterSpec("brute", 3.0), CharacterSpec(str(chain_file), 2.0))
    # No clear disc at the start: 300 agents spread over the overview's square, as the shares are counted in view.
    config = PipelineConfig(agents=300, seed=4, characters=cast, cull=cull, ai=AIConfig(armed_share=1.0, start_clear=0.0), survivor=False)
    size = (480, 270)
    with Offscreen(gl_context, size) as target, CrowdPipeline(gl_context, config) as p:
        assert p.ai.cast == (150, 90, 60)
        p.camera = p.overview_camera(size[0] / size[1])
        _tinted(p, [(255, 0, 0), (0, 255, 0), (0, 0, 255)])
        for _ in range(8):
            p.frame(target.framebuffer, 1 / 30)
        p.refresh_counts()
        visible = p.renderer.last["cast_visible"]
        shares = np.array([5, 3, 2]) / 10
        assert sum(visible) >= 0.93 * p.agents  # (the overview's frustum cuts the square's corners: 284 to 291 of 300 over seeds 1 to 8)
        assert np.all(np.abs(np.array(visible) / sum(visible) - shares) < 0.02), visible
        assert p.processor.nan_rows() == 0
        image = target.image().astype(int)
        dominant = np.argmax(image, axis=2)
        strong = image.max(axis=2) - np.sort(image, axis=2)[..., 1] > 40  # a clearly red, green or blue pixel
        for k in range(3):
            assert np.count_nonzero(strong & (dominant == k)) > 50, f"character {k} drew too few pixels"
        # The weapons of both armed characters, each in its own character's hand.
        assert p.weapons is not None and len(p.weapons.names) == 3  # pipe, axe; sledge
        held = p.weapons.drawn[1]
        assert set(np.unique(held)) >= {2} and set(np.unique(held)) & {0, 1}
        assert p.weapon_error_mm() < 0.05


def test_the_crowd_resizes_from_zero_to_thousands_and_back_without_leaks(gl_context):
    from crowd.gl import gpu_bytes

    config = PipelineConfig(agents=0, characters=(CharacterSpec("zombie", 3.0), CharacterSpec("brute", 1.0)), survivor=True)
    with Offscreen(gl_context, (96, 54)) as target, CrowdPipeline(gl_context, config) as p:
        p.frame(target.framebuffer, 1 / 30)
        empty = p.gpu_bytes()
        for n in (5, 3000, 7, 0, 1200, 0):
            p.set("agents", n)
            p.frame(target.framebuffer, 1 / 30)
            assert p.ai.cast == cast_counts(n, (3.0, 1.0)) and p.processor.layout.counts == p.counts == p.ai.cast + (1,)
            assert p.processor.nan_rows() == 0
        p.refresh_counts()
        assert p.gpu_bytes()["palette"] == empty["palette"]  # the survivor's row alone


# -- the AI: each agent moves and animates as its character


def test_each_agent_plays_its_own_characters_clips_at_its_speeds(cast):
    motions = [motion_for(c, b, r) for c, r, b in cast]
    ai = CrowdAI(1000, 3, motions, AIConfig(armed_share=0.0), shares=(5, 3, 2))
    assert ai.cast == (500, 300, 200)
    for _ in range(30):
        ai.step(1 / 30)
    layers = ai.layers()
    first = cast_firsts(ai.cast)
    for k, m in enumerate(motions):
        block = slice(first[k], first[k + 1])
        assert np.all(ai.kind[block] == k)
        assert layers[block, 0, CLIP].tolist() == [m.clip["idle"]] * ai.cast[k]
        assert np.allclose(ai.walk_top[block], m.walk_speed * ai.speed_factor[block])
    # The chain has no attack, hit or death clip: it neither strikes nor falls.
    chain = np.arange(first[2], first[3])
    ai.hit(chain)
    assert np.all(ai.state[chain] < 2)  # not hit, not dying (crowd.sim.ai: WANDER, CHASE)
    assert ai.check() == []


def test_a_resize_keeps_each_characters_agents_where_they_were(cast):
    motions = [motion_for(c, b, r) for c, r, b in cast]
    ai = CrowdAI(400, 2, motions, shares=(2, 1, 1))
    ai.step(0.2)
    x = ai.x.copy()
    old = ai.cast
    ai.resize(100)
    for was, now, kept in cast_moves(old, ai.cast):
        assert np.array_equal(ai.x[now:now + kept], x[was:was + kept])
    assert all(np.all(ai.kind[a:b] == k) for k, (a, b) in enumerate(zip(cast_firsts(ai.cast)[:-1], cast_firsts(ai.cast)[1:])))


# -- scene files and flags


def test_a_scene_names_its_cast_and_saves_it_back(tmp_path, chain_file):
    path = tmp_path / "mixed.toml"
    path.write_text(f'''
[scene]
agents = 12

[[characters]]
model = "brute"
share = 2
roles = {{ walk = "shamble" }}
speed = {{ shamble = 1.5 }}

[[characters]]
model = "{chain_file.name}"
share = 1
model_scale = 1.0
''')
    (tmp_path / chain_file.name).write_bytes(chain_file.read_bytes())
    scene = load_scene(path)
    assert [(str(c.model) if c.model == "brute" else c.model.name, c.share) for c in scene.characters] == [("brute", 2.0), ("chain.gltf", 1.0)]
    assert scene.characters[0].clip_speed == {"shamble": 1.5} and scene.characters[1].model_scale == 1.0
    save_scene(scene, tmp_path / "again.toml")
    again = load_scene(tmp_path / "again.toml")
    assert again.characters == scene.characters
    config = scene.pipeline_config()
    assert [s.share for s in config.cast()] == [2.0, 1.0]


@pytest.mark.parametrize("text, words", [
    ('[[characters]]\nmodel = "brute"\nshare = 0\n', "characters[0].share"),
    ('[[characters]]\nmodel = "brute"\nshare = "lots"\n', "characters[0].share"),
    ('[[characters]]\nmodel = "brute"\ncolour = 1\n', "unknown key 'colour'"),
    ('[[characters]]\nmodel = 3\n', "characters[0].model"),
    ('[scene]\nmodel = "brute"\n[[characters]]\nmodel = "zombie"\n', "with [[characters]]"),
    ('characters = 5\n', "array of tables"),
    ('[[characters]]\nmodel = "zombie"\nroles = { fly = "x" }\n', "unknown role 'fly'"),
    ("".join('[[characters]]\nmodel = "zombie"\n' for _ in range(257)), "at most 256"),
])
def test_a_bad_cast_is_one_line_naming_the_file_and_the_entry(tmp_path, text, words):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(SceneError) as info:
        load_scene(path)
    assert str(path) in str(info.value) and words in str(info.value) and "\n" not in str(info.value)


def test_the_default_scene_is_a_mixed_horde_and_a_model_makes_it_one_character():
    assert [c.model for c in Scene().characters] == ["zombie", "brute"]
    assert [c.model for c in load_scene(ROOT / "scenes" / "horde.toml").characters] == ["zombie", "brute"]
    assert [c.model for c in Scene().with_overrides(model="brute").characters] == ["brute"]
    with pytest.raises(SceneError, match="belongs to one character"):
        Scene().with_overrides(roles={"walk": "run"})


def test_the_characters_flag(tmp_path):
    out = subprocess.run([sys.executable, "-m", "app.demo", "--headless", "--frames", "2", "--agents", "8", "--size", "64x36",
                          "--characters", "zombie=1,brute=1", "--stats", str(tmp_path / "s.json"), "--screenshot", str(tmp_path / "s.png")],
                         capture_output=True, text=True, timeout=180, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    import json

    stats = json.loads((tmp_path / "s.json").read_text())
    assert [(c["name"], c["agents"]) for c in stats["cast"]] == [("zombie", 4), ("brute", 4), ("survivor", 1)]  # and the player's
    bad = subprocess.run([sys.executable, "-m", "app.demo", "--headless", "--characters", "zombie=1,nowhere.glb=2"],
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0 and "nowhere.glb" in bad.stderr


@pytest.mark.parametrize("cull", ["gpu", "feedback"])
def test_a_cast_of_many_armed_characters_draws_every_weapon_on_the_gpu_paths(gl_context, cull):
    """Nine zombies and nine brutes: 27 weapon meshes, more than the 16 the GPU path once listed, each
    drawn in its own character's hand, as the CPU path draws them at the same GL level (the 4.1 path's
    processor holds no feet, so its poses are not the compute path's)."""
    if cull == "gpu" and not has_compute(gl_context):
        pytest.skip("no GL 4.3 here")
    cast = tuple(CharacterSpec(model, 1.0) for model in ("zombie", "brute") * 9)
    drawn = {}
    for path in ("cpu", cull):
        config = PipelineConfig(agents=360, seed=6, characters=cast, cull=path, gl="4.1" if cull == "feedback" else "auto",
                                ai=AIConfig(armed_share=1.0), survivor=False, impostors="off", ai_path="cpu")  # (one crowd on every path)
        with Offscreen(gl_context, (160, 90)) as target, CrowdPipeline(gl_context, config) as p:
            assert len(p.weapons.names) == 27
            p.camera = p.overview_camera(16 / 9)
            for _ in range(4):
                p.frame(target.framebuffer, 1 / 30)
            p.refresh_counts()
            # (what was drawn; a GPU path's per-mesh "count" is the placed weapons its passes may draw)
            drawn[path] = ({k: p.weapons.last[k] for k in ("drawn", "draws", "triangles")}, target.image())
            assert p.weapon_error_mm() < 0.05
    assert drawn["cpu"][0] == drawn[cull][0] and drawn["cpu"][0]["drawn"] > 100 and drawn["cpu"][0]["draws"] > 27
    assert np.array_equal(drawn["cpu"][1], drawn[cull][1])
