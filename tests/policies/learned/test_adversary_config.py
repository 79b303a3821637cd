"""``AdversaryConfig``: every shared adversary option is checked when the config is built,
the error naming ``AdversaryConfig.<field>``."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from policies.learned.adversary_config import AdversaryConfig
from policies.learned.windows import WindowConfig
from riskflow_env.config import DynamicsConfig


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"lambda_adv": math.nan}, "AdversaryConfig.lambda_adv must be a finite number, got nan"),
        ({"lambda_map": math.inf}, "AdversaryConfig.lambda_map must be a finite number, got inf"),
        ({"lambda_map": -1.0}, "AdversaryConfig.lambda_map must be >= 0 [1/m^2], got -1.0"),
        ({"rank_threshold": True}, "AdversaryConfig.rank_threshold must be a finite number"),
        ({"planning_interval": 0.33}, "AdversaryConfig.planning_interval: 0.33 s is not a"),
        ({"planning_interval": 0.0}, "AdversaryConfig.planning_interval: 0.0 s is not a"),
        ({"planning_interval": "0.5"}, "AdversaryConfig.planning_interval must be a number [s]"),
        ({"device": "nope"}, "AdversaryConfig.device: 'nope' is not a torch device"),
        ({"device": "meta"}, "AdversaryConfig.device: 'meta' is not supported"),
        ({"guidance_horizon": 0}, "AdversaryConfig.guidance_horizon must be an int >= 1, got 0"),
        ({"threads": 0}, "AdversaryConfig.threads must be an int in [1, 256], got 0"),
        ({"threads": 1000}, "AdversaryConfig.threads must be an int in [1, 256], got 1000"),
        ({"target": "all"}, "AdversaryConfig.target must be one of ('others', 'ego'), got 'all'"),
        ({"seed": -1}, "AdversaryConfig.seed must be an int >= 0, got -1"),
        ({"hold_distance": True}, "AdversaryConfig.hold_distance must be a finite number >= 0"),
    ],
)
def test_bad_values_are_refused_when_built(changes, message):
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        AdversaryConfig(**changes)


def test_numpy_float_hold_distance_is_a_number():
    hold = AdversaryConfig(hold_distance=np.float32(0.1)).hold_distance
    assert type(hold) is float and hold == 0.1


def test_planning_interval_is_a_multiple_of_the_windows_time_step():
    """The env's dt is the window config's when one is given (the plan horizon is the
    model's: checked when an episode starts)."""
    fine = WindowConfig(dynamics=DynamicsConfig(dt=0.05))
    assert AdversaryConfig(planning_interval=0.25, window_config=fine).planning_interval == 0.25
    with pytest.raises(TypeError, match=r"^AdversaryConfig.window_config must be None or a Wind"):
        AdversaryConfig(window_config={"dynamics": None})
