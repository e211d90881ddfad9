import pytest
import numpy as np
from PIL import Image

from crowd.gl import describe


def test_headless_egl_context_has_gl33_or_better(gl_context):
    info = describe(gl_context)
    assert info["version_code"] >= 330
    assert info["gl_renderer"]


def test_preview_draws_the_zombie(tmp_path, zombie):
    from bench.preview import render_sheet

    out = render_sheet(zombie, ["shamble"], 2, 96, tmp_path / "sheet.png")
    img = np.asarray(Image.open(out).convert("RGB")).astype(int)
    background = np.array([0.16, 0.18, 0.22]) * 255
    skin = np.abs(img - background).sum(-1) > 40
    assert skin.mean() > 0.05  # the figure and the ground cover part of the frame


def test_preview_frames_the_skinned_pose_and_labels_each_row(tmp_path, zombie):
    """A character whose bind meshes are 100 times its skinned size (the inverse binds scale them back)
    fills its cells as the zombie does: the sheet is framed on skinned poses, not bind positions. Each
    row has a label strip with its clip's name drawn in it."""
    import dataclasses

    from bench.preview import LABEL_HEIGHT, render_sheet

    shrink = np.diag([0.01, 0.01, 0.01, 1.0])
    skeleton = dataclasses.replace(zombie.skeleton, inverse_bind=np.asarray(zombie.skeleton.inverse_bind) @ shrink)
    meshes = [dataclasses.replace(m, positions=m.positions * 100.0) for m in zombie.meshes]
    giant = dataclasses.replace(zombie, skeleton=skeleton, meshes=meshes)
    background = np.array([0.16, 0.18, 0.22]) * 255
    coverage = {}
    for name, character in (("zombie", zombie), ("giant bind", giant)):
        out = render_sheet(character, ["idle", "death"], 2, 96, tmp_path / f"{name}.png")
        img = np.asarray(Image.open(out).convert("RGB")).astype(int)
        assert img.shape == (2 * (96 + LABEL_HEIGHT), 2 * 96, 3)
        for row in range(2):
            strip = img[row * (96 + LABEL_HEIGHT): row * (96 + LABEL_HEIGHT) + LABEL_HEIGHT]
            assert (strip.min(axis=2) > 180).sum() > 40  # light text on the dark strip
        coverage[name] = (np.abs(img - background).sum(-1) > 40).mean()
    assert coverage["giant bind"] == pytest.approx(coverage["zombie"], rel=0.05)
