"""Agents drawn only as impostors get their key alone from the processor (crowd.draw.far_agents): the
picture is the same to the bit as with every row whole, in a steady view and across a camera cut; their
rows hold nothing past the key but the socket chain of a weapon held, and their foot lock is free."""

from __future__ import annotations

import numpy as np
import pytest

from crowd.frame import Camera
from crowd.gl import Offscreen
from crowd.pipeline import CrowdPipeline
from crowd.pipeline_config import PipelineConfig
from crowd.sim.config import AIConfig

SIZE = (200, 120)
NEAR = Camera(eye=np.array([0.0, 1.8, -6.0]), target=np.array([0.0, 1.0, 10.0]), aspect=SIZE[0] / SIZE[1])
CUT = Camera(eye=np.array([-14.0, 1.8, -6.0]), target=np.array([-14.0, 1.0, 10.0]), aspect=SIZE[0] / SIZE[1])


def run(ctx, far: bool, frames: int, cut_at: int | None = None, foot_lock: bool = True):
    config = PipelineConfig(agents=1200, seed=5, ai_path="gpu", impostors="on", foot_lock=foot_lock,
                            ai=AIConfig(start_clear=0.0, half_extent=20.0))
    images = []
    with Offscreen(ctx, SIZE) as target, CrowdPipeline(ctx, config) as p:
        assert p.ai_path == "gpu" and p.processor.path == "compute"
        if not far:  # every row whole: the reference
            p.processor.key_alone_beyond = lambda *args, **kwargs: None
        p.camera = NEAR
        p.renderer.set_impostor_distance(8.0)
        for f in range(frames):
            if f == cut_at:
                p.camera = CUT
                if not far:
                    p.sync.reset()  # (the cut drops the kept palettes on the far path: the reference does too)
            p.frame(target.framebuffer, 1 / 60)
            if cut_at is not None and f >= cut_at:
                images.append(target.image())
        images.append(target.image())
        crowd = p.gpu_crowd.store()
        eye = np.asarray(p.camera.eye)
        distance = np.hypot(np.hypot(crowd.x - eye[0], crowd.z - eye[2]), eye[1])
        beyond = None if p.processor._far is None else p.processor._far[3]
        holds = crowd.weapon >= 0
        palette = p.processor.read_palette()
        lock = [None if part.lock_state is None else np.frombuffer(part.lock_state.read(), np.float32).reshape(-1, 4) for part in p.processor.parts]
        socket = next(iter(p.character.sockets.values()))
        parents = p.character.skeleton.parents
        return images, distance, beyond, palette, lock, socket, parents, p.counts, holds


@pytest.fixture
def ctx(compute_context):
    return compute_context


def test_far_agents_get_their_key_alone_and_the_picture_does_not_change(ctx):
    images, distance, beyond, palette, lock, socket, parents, counts, holds = run(ctx, True, 20)
    reference = run(ctx, False, 20)[0]
    assert beyond is not None and 100 <= np.count_nonzero(distance > beyond) < len(distance) - 20
    np.testing.assert_array_equal(images[-1], reference[-1])
    kept = set()
    j = socket
    while j >= 0:
        kept.add(j)
        j = int(parents[j])
    skipped = [j for j in range(palette.shape[1]) if j not in kept]
    far, near = np.flatnonzero(distance > beyond + 1.0), np.flatnonzero(distance < beyond - 1.0)
    first = counts[0]  # (the first character's block: its rows' joints are the skeleton's)
    far, near = far[far < first], near[near < first]
    armed, unarmed = far[holds[far]], far[~holds[far]]
    assert len(armed) and len(unarmed) and len(near)
    assert not np.any(palette[armed][:, skipped]) and not np.any(palette[unarmed]), "a far agent's skipped joints were written"
    assert np.all(np.abs(palette[armed][:, sorted(kept)]).sum(axis=(2, 3)) > 0.5), "a far armed agent's socket chain is missing"
    assert np.all(np.abs(palette[near]).sum(axis=(2, 3)) > 0.5), "a near agent's row is not whole"
    if lock[0] is not None:
        legs = len(lock[0]) // first
        assert not np.any(lock[0].reshape(first, legs, 4)[far]), "a far agent's foot lock holds a step"


def test_a_camera_cut_draws_what_whole_rows_draw(ctx):
    """The new view's near agents were far from the old one: their kept palettes are dropped and they are
    drawn from this frame's, frame after frame, as the reference that drops its palettes there draws them:
    to the bit without the foot lock. With it, an agent that comes near starts with its feet free (as a new
    agent does) where the reference's had held a step: a few of its pixels differ (23 to 30 of 24,000)."""
    images = run(ctx, True, 14, cut_at=10, foot_lock=False)[0]
    reference = run(ctx, False, 14, cut_at=10, foot_lock=False)[0]
    for got, want in zip(images, reference):
        np.testing.assert_array_equal(got, want)
    images = run(ctx, True, 14, cut_at=10)[0]
    reference = run(ctx, False, 14, cut_at=10)[0]
    for got, want in zip(images, reference):
        assert np.count_nonzero(np.abs(got.astype(int) - want.astype(int)).max(axis=-1)) <= 0.005 * got.shape[0] * got.shape[1]
