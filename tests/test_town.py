"""Streets to fight in (issue 22, point 3): the built-in town, its obstacle field against the exact boxes,
a crowd that never ends a step inside an obstacle, spawns on the streets, chasers that find their way
around a building, and a town drawn and shadowed only where the scene has one."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crowd.anim.roles import bake_roles, match_roles
from crowd.asset.town import PERIOD, SDF_CELL, TILE, Box, box_distance, build_town
from crowd.gl import Offscreen, has_compute
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import PipelineConfig
from crowd.scene import Scene
from crowd.sim.ai import CrowdAI, PlayerScript
from crowd.sim.config import AIConfig
from crowd.sim.motion import motion_for
from crowd.sim.obstacles import CLEARANCE


@pytest.fixture(scope="module")
def town():
    return build_town()


@pytest.fixture(scope="module")
def motion(zombie):
    roles, _ = match_roles(zombie.clips)
    return motion_for(zombie, bake_roles(zombie, roles), roles)


def _repeated(boxes):
    """The district's boxes and their copies one period away, for exact distances anywhere in it."""
    return [Box(b.x + dx, b.z + dz, b.half_x, b.half_z, b.yaw, b.height) for b in boxes for dx in (-PERIOD, 0.0, PERIOD)
            for dz in (-PERIOD, 0.0, PERIOD)]


def _exact(boxes, x, z):
    return box_distance(boxes, np.mod(x, PERIOD), np.mod(z, PERIOD))


def test_the_district_has_streets_buildings_cars_and_barriers(town):
    names = {p.mesh.name for p in town.pieces}
    assert {"car", "barrier", "kerbs"} <= names and sum(n.startswith("building_") for n in names) >= 4
    assert 40 <= len([b for b in town.boxes if b.height > 5]) and town.obstacles().free_share > 0.6
    # The streets are clear: their centre lines (multiples of TILE) have no building on them.
    buildings = [b for b in town.boxes if b.height > 5]
    along = np.linspace(0, PERIOD, 400)
    assert np.all(box_distance(_repeated(buildings), along, np.zeros_like(along)) > 5.0)


def test_the_obstacle_field_is_within_its_bound_of_the_exact_distance(town):
    """Bilinear in cells of SDF_CELL, the field is off by at most a cell's half diagonal where the
    distance bends along a line across the cells (a box's middle inside it, the ridge between two boxes
    outside): searched on a fine grid around every box, not sampled (50,000 random points had found 0.10 m)."""
    o = town.obstacles()
    boxes = _repeated(town.boxes)
    worst = 0.0
    for b in town.boxes:
        extent = math.hypot(b.half_x, b.half_z) + 1.0
        u = np.linspace(-extent, extent, 161)
        x, z = np.meshgrid(b.x + u, b.z + u, indexing="ij")
        near_boxes = [c for c in boxes if math.hypot(c.x - b.x, c.z - b.z) < extent + math.hypot(c.half_x, c.half_z) + 2.0]
        exact = box_distance(near_boxes, x, z)
        near = exact < 2.0
        worst = max(worst, float(np.max(np.abs(o.distance(x, z) - exact)[near])))
    assert worst <= SDF_CELL / math.sqrt(2.0), worst
    assert CLEARANCE - SDF_CELL / math.sqrt(2.0) > 0.15  # so an agent the field keeps CLEARANCE away is clear of every box


def test_ten_thousand_agents_over_sixty_seconds_never_end_a_step_inside_an_obstacle(town, motion):
    """Every step, every agent is CLEARANCE (within 1 cm) from the obstacles by the field, which the
    field's searched bound puts outside every box; every 15th step that is checked by the exact distance
    too, for the agents the field puts within a metre of one."""
    o = town.obstacles()
    boxes = _repeated(town.boxes)
    ai = CrowdAI(10_000, 4, motion, AIConfig(workers=1), obstacles=o)
    script = PlayerScript(9.0)
    closest = np.inf
    for step in range(int(60 * 30)):
        script.update(ai)
        ai.step(1 / 30)
        d = o.distance(ai.x, ai.z)
        assert d.min() >= CLEARANCE - 0.01, (step, float(d.min()))
        near = np.flatnonzero(d < 1.0)
        if near.size and step % 15 == 0:  # (every step the field's bound, searched above, already puts them outside)
            closest = min(closest, float(_exact(boxes, ai.x[near], ai.z[near]).min()))
    assert closest > 0.0 and ai.check() == []
    assert ai.counts()["chase"] + ai.counts()["attack"] > 0  # it played: zombies chased the player through the streets


@pytest.mark.parametrize("dt", [1.0 / 60.0, 10.0])
def test_a_thousand_agents_spawned_at_one_point_by_a_wall(town, motion, dt):
    """The stiff case in the town: a pile at one point 0.1 m from a building's wall (inside the clearance),
    stepped 1/60 s or 10 s (clamped) at a time: they come apart and none is left in the clearance; a step
    of 0 s changes nothing."""
    o = town.obstacles()
    wall = next(b for b in town.boxes if b.height > 5 and b.yaw == 0.0)
    ai = CrowdAI(1000, 2, motion, AIConfig(workers=1, half_extent=60.0), obstacles=o, origin=(wall.x, wall.z))
    ai.x[:] = wall.x + wall.half_x + 0.1
    ai.z[:] = wall.z
    ai.step(0.0)
    assert np.all(ai.x == wall.x + wall.half_x + 0.1) and np.all(ai.z == wall.z)
    for _ in range(30):
        ai.step(dt)
    assert o.distance(ai.x, ai.z).min() >= CLEARANCE - 0.01
    assert _exact(_repeated(town.boxes), ai.x, ai.z).min() > 0.0 and ai.check() == []
    assert np.ptp(ai.x) + np.ptp(ai.z) > 2.0  # the pile came apart


def test_the_horde_spawns_on_the_streets(town, motion):
    o = town.obstacles()
    ai = CrowdAI(20_000, 7, motion, AIConfig(workers=1, corpse_time=0.0, health=1, start_clear=0.0), obstacles=o)
    assert o.distance(ai.x, ai.z).min() >= CLEARANCE + 0.1 - 1e-9  # spawned anywhere: on streets, sidewalks, yards
    assert ai.half_extent > 0.5 * math.sqrt(20_000 * AIConfig().area_per_agent)  # the world grows by the ground the town takes
    ai.hit(np.arange(0, 20_000, 3))  # killed: they respawn at the world's edges after their death and corpse_time
    for _ in range(100):
        ai.step(1 / 30)
    respawned = np.flatnonzero(ai.spawned_step > 0)
    assert respawned.size and o.distance(ai.x[respawned], ai.z[respawned]).min() >= CLEARANCE - 0.01


def test_a_chaser_finds_its_way_round_a_building(town, motion):
    """The player stands in the street behind a building; a zombie on the far side, which a straight line
    would press into the wall, goes round by the flow field and reaches the player."""
    o = town.obstacles()
    b = max((b for b in town.boxes if b.height > 5), key=lambda b: b.half_x)
    ai = CrowdAI(1, 3, motion, AIConfig(workers=1, half_extent=60.0, notice_radius=40.0, forget_radius=60.0, think_radius=60.0, reaction_min=0.0,
                                         reaction_max=0.0, speed_min=1.0, speed_max=1.0, runner_share=1.0), obstacles=o, origin=(b.x, b.z))
    ai.player = np.array([b.x, b.z - b.half_z - 2.0])  # on one side of the building
    ai.x[:], ai.z[:] = b.x, b.z + b.half_z + 2.0  # and the zombie on the other
    ai.vx[:] = ai.vz[:] = 0.0
    reached = False
    for step in range(30 * 30):
        ai.step(1 / 30)
        if math.hypot(ai.x[0] - ai.player[0], ai.z[0] - ai.player[1]) < AIConfig().attack_reach + 0.5:
            reached = True
            break
    assert reached, (ai.x[0], ai.z[0], ai.player)


def test_the_town_is_drawn_and_shadowed_only_where_the_scene_has_one(gl_context):
    size = (320, 180)
    scene = Scene(agents=60, town=True, survivor=True)
    with Offscreen(gl_context, size) as target, CrowdPipeline(gl_context, scene.pipeline_config()) as p:
        p.camera = p.default_camera(size[0] / size[1])
        for _ in range(3):
            p.frame(target.framebuffer, 1 / 30)
        assert {"town", "town_cull"} <= set(p.passes_run) and p.gpu_bytes()["town"] > 0
        assert p.town.last["instances"] > 10 and p.town.last["shadow_instances"] > 0
        with_town = target.image().astype(int)
    with Offscreen(gl_context, size) as target, CrowdPipeline(gl_context, Scene(agents=60, town=False).pipeline_config()) as p:
        p.frame(target.framebuffer, 1 / 30)
        assert p.town is None and "town" not in p.passes_run and "town" not in p.gpu_bytes() and p.obstacles is None
    # Buildings: the picture has tall light walls the plane never shows.
    assert np.mean(with_town.mean(axis=2) > 140) > 0.05


def test_occlusion_culling_in_the_town_hides_nothing_that_shows(gl_context):
    """Seen from the street, buildings hide much of the crowd: occlusion culling (against the last
    frame's depth, buildings in it) drops some agents, and the picture is the same as without it."""
    if not has_compute(gl_context):
        pytest.skip("occlusion culling is the GPU cull path's")
    size = (320, 180)
    pictures, culled = {}, {}
    for occlusion in (False, True):
        config = Scene(agents=2000, town=True, survivor=False, occlusion=occlusion, cull="gpu").pipeline_config()
        with Offscreen(gl_context, size) as target, CrowdPipeline(gl_context, config) as p:
            # At eye height in the street along z, looking along it: the blocks on either side hide the rest.
            p.camera.eye = np.array([0.0, 1.7, 30.0])
            p.camera.target = np.array([0.0, 1.5, 0.0])
            p.camera.aspect = size[0] / size[1]
            p.frame(target.framebuffer, 1 / 30)
            p.frame(target.framebuffer, 0.0)  # the same crowd again, now against this frame's depth
            p.refresh_counts()
            pictures[occlusion] = target.image().astype(int)
            culled[occlusion] = p.renderer.last["visible"]
    assert culled[True] < culled[False]  # occlusion culled agents behind the buildings
    assert np.abs(pictures[True] - pictures[False]).max() <= 2  # and none that shows


def test_the_town_culls_districts_only_where_all_their_pieces_are_out(town, gl_context):
    """The district spheres culled first hold every placement's sphere, wherever the eye is: culling a
    district never drops a piece the per-placement test would keep."""
    from crowd.draw.town import TownRenderer

    with TownRenderer(gl_context, town, shadows=False) as renderer:
        for eye in ([0.0, 20.0, 0.0], [1234.5, 3.0, -987.25], [-96.0, 400.0, 191.9]):
            placed = renderer._place(np.array(eye))
            centre = placed["centres"][placed["district"]]
            reach = np.hypot(placed["xz"][:, 0] - centre[:, 0], placed["xz"][:, 1] - centre[:, 2]) + placed["radius"]
            assert placed["centres"][:, 1].max() == 0.0 and reach.max() <= placed["district_radius"] + 1e-9


def test_the_follow_camera_stays_out_of_buildings(town):
    """Behind the survivor with a building's wall between: the camera comes in to the survivor's side of
    it (not inside); with nothing in the way, or only a car, it keeps its distance."""
    from app.camera import WALL_CLEARANCE, FollowControl
    from crowd.frame import Camera

    walls = FollowControl.walls_in(town.obstacles())
    building = next(b for b in town.boxes if b.height > 5 and b.yaw == 0.0)
    follow = FollowControl(yaw=-math.pi / 2)  # the camera sits toward -x of the survivor: into the building
    camera = Camera(eye=np.zeros(3), target=np.ones(3))
    survivor = (building.x + building.half_x + 1.0, building.z)  # 1 m off the building's +x wall
    follow.apply(camera, survivor)
    assert camera.eye[0] < building.x + building.half_x - 1.0  # unstopped, it would be inside
    follow.apply(camera, survivor, walls)
    assert walls.distance(camera.eye[0], camera.eye[2]) >= WALL_CLEARANCE - 1e-9
    assert camera.eye[1] - camera.target[1] == pytest.approx(follow.distance * math.sin(follow.pitch))  # at its height
    pressed = (building.x + building.half_x + CLEARANCE, building.z)  # backed against the wall: no room behind
    follow.apply(camera, pressed, walls)
    assert walls.distance(camera.eye[0], camera.eye[2]) > 0.0 and np.all(np.isfinite(camera.eye))
    assert abs(camera.eye[0] - camera.target[0]) > 0.1  # never straight down (a view with no up)
    car = next(b for b in town.boxes if 1.0 < b.height < 2.0)
    open_ground = FollowControl(yaw=0.0)
    open_ground.apply(camera, (car.x, car.z - 3.0), walls)  # a car in the way: seen over
    assert np.linalg.norm(camera.eye - camera.target) == pytest.approx(open_ground.distance)


def test_the_town_culled_on_the_gpu_draws_what_the_numpy_cull_draws(gl_context):
    """Where the context runs compute shaders the town's placements are culled on the GPU: the same
    placements in the view and each cascade and the same picture as the numpy cull, along a flight that
    crosses districts (the GPU's buffers made again for the districts in sight) and looks up at nothing."""
    from crowd.frame import Camera

    if not has_compute(gl_context):
        pytest.skip("the GPU cull needs GL 4.3 compute shaders")
    size = (240, 135)
    flight = [((x, 6.0, 40.0), (x + 30.0, 1.0, 10.0)) for x in (0.0, 150.0, 230.0, 420.0)] + [((0.0, 2.0, 0.0), (0.0, 300.0, 1.0))]
    seen = {}
    for cull in ("gpu", "cpu"):
        scene = Scene(agents=40, town=True, cull=cull, ai_path="cpu")
        with Offscreen(gl_context, size) as target, CrowdPipeline(gl_context, scene.pipeline_config()) as p:
            assert p.town.gpu_cull == (cull == "gpu")
            seen[cull] = []
            for eye, target_point in flight:
                p.camera = Camera(eye=np.array(eye), target=np.array(target_point), aspect=size[0] / size[1])
                p.frame(target.framebuffer, 1 / 30)
                seen[cull].append((dict(p.town.last), target.image().astype(int)))
            gpu_bytes = p.gpu_bytes()["town"]
        assert gpu_bytes > 0
    for (gpu_last, gpu_image), (cpu_last, cpu_image) in zip(seen["gpu"], seen["cpu"]):
        assert gpu_last == cpu_last
        assert np.count_nonzero(np.abs(gpu_image - cpu_image).max(axis=-1) > 8) <= 0.001 * gpu_image[..., 0].size
    assert any(last["instances"] > 20 for last, _ in seen["gpu"]) and seen["gpu"][-1][0]["instances"] < seen["gpu"][0][0]["instances"]
