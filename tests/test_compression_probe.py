"""bench.compression_probe (issue 21, point 4's format study): the encodings decode within their steps,
and the bit widths it picks keep a clip within the bound they were picked for."""

from __future__ import annotations

import numpy as np
import pytest

from bench.compression_probe import ClipTracks, decode_rotation, per_track_bits, uniform_bits
from crowd import transforms as tf


@pytest.mark.parametrize("drop_w", [False, True])
def test_a_rotation_track_decodes_within_its_quantisation_step(drop_w):
    rng = np.random.default_rng(3)
    axis = rng.normal(size=3)
    q = tf.quat_from_axis_angle(axis / np.linalg.norm(axis), np.linspace(-2.5, 2.5, 40))  # crosses w's sign change
    decoded = decode_rotation(q, 12, drop_w)
    # The same rotation up to sign, within a few steps of the track's range (4095 steps).
    dots = np.abs(np.sum(decoded * q, axis=1))
    angle = 2.0 * np.arccos(np.minimum(dots, 1.0))
    assert angle.max() < 8.0 * 2.0 / 4095


def test_the_widths_picked_keep_the_clip_within_the_bound(zombie):
    clip = ClipTracks(zombie, zombie.clip("shamble"))
    for drop_w in (False, True):
        rb, tb = uniform_bits([clip], 0.5, drop_w)
        assert clip.error_mm(np.full(clip.joints, rb), np.full(clip.joints, tb), drop_w) <= 0.5
        assert clip.error_mm(np.full(clip.joints, rb - 2), np.full(clip.joints, tb), drop_w) > 0.25  # the search found a real edge
        rot, tr = per_track_bits(clip, (rb, tb), 0.5, drop_w)
        assert clip.error_mm(rot, tr, drop_w) <= 0.5
        assert clip.nbytes(rot, tr, drop_w) < clip.nbytes(np.full(clip.joints, rb), np.full(clip.joints, tb), drop_w)
