"""The frame's pass timer (crowd.timing.PassTimer): a sample per span on either clock, GPU samples read
RING - 1 frames later (or at a drain), and a span left by an exception still counted and closed."""

from __future__ import annotations

import time

import numpy as np
import pytest

from crowd.timing import RING, PassTimer


def test_cpu_spans_sample_each_use_in_order_of_first_use():
    timer = PassTimer(None)
    for _ in range(3):
        with timer.cpu("ai"):
            time.sleep(0.002)
        with timer.gpu("draw"):  # no context: a GPU span times nothing
            pass
        timer.end_frame()
    assert timer.order == ["ai", "draw"] and timer.clock == {"ai": "cpu", "draw": "gpu"}
    ai = np.asarray(timer.samples["ai"])
    assert len(ai) == 3 and np.all(ai >= 2.0)
    assert "draw" not in timer.samples


def test_gpu_spans_come_back_ring_minus_one_frames_later(gl_context):
    timer = PassTimer(gl_context)
    try:
        for frame in range(RING + 2):
            with timer.gpu("clear"):
                gl_context.clear(0.1, 0.2, 0.3)
            timer.end_frame()
            assert len(timer.samples.get("clear", [])) == max(frame - (RING - 2), 0)
        timer.end_frame(drain=True)
        got = np.asarray(timer.samples["clear"])
        assert len(got) == RING + 2 and np.all(got >= 0.0)
    finally:
        timer.release()


def test_a_span_left_by_an_exception_is_counted_and_the_query_closed(gl_context):
    timer = PassTimer(gl_context)
    try:
        with pytest.raises(ValueError):
            with timer.gpu("bad"):
                raise ValueError("in the pass")
        with pytest.raises(ValueError):
            with timer.cpu("bad_cpu"):
                raise ValueError("in the pass")
        with timer.gpu("bad"):  # the slot's query was ended: a query can begin again
            pass
        timer.end_frame(drain=True)
        assert len(timer.samples["bad"]) == 2 and len(timer.samples["bad_cpu"]) == 1
    finally:
        timer.release()
