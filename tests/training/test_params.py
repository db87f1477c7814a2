"""Tests of trace3d.training.params: the 2DGS schedule, its scaling and the parameters' validation."""

from __future__ import annotations

import pytest

from tests.plane_scene import single_thread  # noqa: F401  (autouse fixture)
from trace3d.errors import ConfigError
from trace3d.params import from_mapping
from trace3d.training import TrainParams


def test_schedule_scaling_and_reference_defaults():
    ref = TrainParams.reference_2dgs().schedule()
    assert ref == {"iterations": 30000, "densify_from": 500, "densify_until": 15000, "densify_interval": 100,
                   "opacity_reset_interval": 3000, "sh_degree_interval": 1000, "normal_from": 7000,
                   "distortion_from": 3000, "checkpoint_interval": 1000}
    assert TrainParams.reference_2dgs().densify_grad_threshold == 0.0002
    half = TrainParams(schedule_scale=0.5).schedule()
    assert half["iterations"] == 15000 and half["densify_interval"] == 50
    assert TrainParams(schedule_scale=1e-4).scaled("densify_interval") == 1  # never 0


def test_params_validation():
    with pytest.raises(ConfigError, match="unknown"):
        from_mapping(TrainParams, {"iteratons": 5})
    with pytest.raises(ConfigError, match="sh_degree"):
        from_mapping(TrainParams, {"sh_degree": 4})
    with pytest.raises(ConfigError):
        from_mapping(TrainParams, {"schedule_scale": 0})
    p = from_mapping(TrainParams, {"iterations": 7, "background": [1, 1, 1]})
    assert p.iterations == 7 and p.background == [1.0, 1.0, 1.0]
