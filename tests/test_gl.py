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
