"""The frame contracts' checks at a stage's door (crowd.frame): bad values get one line."""

from __future__ import annotations

import numpy as np
import pytest

from crowd.frame import FrameError, Instances


@pytest.mark.parametrize("field", ["position", "yaw", "scale"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_instances_that_are_not_finite_are_one_line(field, bad):
    n = 1000
    values = {"position": np.random.default_rng(0).uniform(-1e5, 1e5, (n, 3)), "yaw": np.zeros(n, np.float32),
              "scale": np.ones(n, np.float32)}
    values[field] = values[field].copy()
    values[field].reshape(-1)[777] = bad
    inst = Instances(values["position"], values["yaw"], values["scale"], np.zeros((n, 4), np.uint8), {})
    with pytest.raises(FrameError, match="^instance positions, headings and scales must be finite$"):
        inst.validate({})
    values[field].reshape(-1)[777] = 2.0  # finite again: accepted, and a scale of 0 is not
    Instances(values["position"], values["yaw"], values["scale"], np.zeros((n, 4), np.uint8), {}).validate({})
    with pytest.raises(FrameError, match="scales must be in"):
        Instances(values["position"], values["yaw"], np.zeros(n, np.float32), np.zeros((n, 4), np.uint8), {}).validate({})
