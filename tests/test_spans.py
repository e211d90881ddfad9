"""crowd.spans: per-agent numpy work over slices side by side, and the checks built on it catching a
bad value in whichever slice it lies."""

from __future__ import annotations

import numpy as np
import pytest

from crowd import spans
from crowd.frame import FrameError, Instances, empty_layers, validate_layers
from crowd.spans import MIN_SPAN, min_max, over_spans


@pytest.fixture
def many_threads(monkeypatch):
    """Four spans whatever this machine's cores (CI has two)."""
    monkeypatch.setattr(spans, "thread_count", lambda: 4)


@pytest.mark.parametrize("n", [0, 1, MIN_SPAN - 1, MIN_SPAN, 2 * MIN_SPAN + 7, 10 * MIN_SPAN + 3])
def test_spans_cover_the_range_in_order(many_threads, n):
    parts = spans.spans(n)
    assert parts[0][0] == 0 and parts[-1][1] == n
    assert all(a[1] == b[0] for a, b in zip(parts, parts[1:]))
    assert len(parts) == max(1, min(4, n // MIN_SPAN))
    assert len(parts) == 1 or min(hi - lo for lo, hi in parts) >= MIN_SPAN


def test_over_spans_returns_in_order_and_raises_after_all_ended(many_threads):
    n = 4 * MIN_SPAN
    out = np.zeros(n)
    assert over_spans(lambda lo, hi: lo, n) == [0, MIN_SPAN, 2 * MIN_SPAN, 3 * MIN_SPAN]

    def work(lo, hi):
        if lo == MIN_SPAN:
            raise ValueError("span 1")
        out[lo:hi] = 1.0

    with pytest.raises(ValueError, match="span 1"):
        over_spans(work, n)
    assert out.sum() == 3 * MIN_SPAN  # the other spans finished before the error surfaced


def test_min_max_carries_nan_from_any_span(many_threads):
    a = np.arange(4 * MIN_SPAN, dtype=np.float32)
    assert min_max(a) == (0.0, 4 * MIN_SPAN - 1.0)
    a[-1] = np.nan
    lo, hi = min_max(a)
    assert np.isnan(lo) and np.isnan(hi)
    assert min_max(np.zeros((0, 3))) == (0.0, 0.0)


@pytest.mark.parametrize("where", [0, MIN_SPAN + 5, 4 * MIN_SPAN - 1])
def test_layer_check_finds_a_bad_value_in_any_span(many_threads, where):
    n = 4 * MIN_SPAN
    layers = empty_layers(n, 4)
    layers[:, 3, 0] = np.arange(n) % 3  # an uneven clip column: the whole-number test runs per span
    layers[:, 3, 2] = 0.5
    assert validate_layers(layers, 3, 0, 4) is not None
    for column, value, message in ((0, 1.5, "whole numbers"), (1, np.nan, "NaN"), (2, 2e6, "weight"), (3, 7.0, "masks")):
        bad = layers.copy()
        bad[where, 3, column] = value
        with pytest.raises(FrameError, match=message):
            validate_layers(bad, 3, 1, 4)


def test_instance_check_finds_a_bad_scale_in_the_last_span(many_threads):
    n = 4 * MIN_SPAN
    inst = Instances(np.zeros((n, 3)), np.zeros(n, np.float32), np.ones(n, np.float32), np.zeros((n, 4), np.uint8))
    inst.validate({})
    inst.scale[-1] = 0.0
    with pytest.raises(FrameError, match="scales"):
        inst.validate({})
    inst.scale[-1] = np.inf
    with pytest.raises(FrameError, match="finite"):
        inst.validate({})
