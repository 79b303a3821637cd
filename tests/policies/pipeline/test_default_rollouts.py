"""The shipped methods' default rollouts stay what they were.

``default_rollouts.npz`` holds 2 s closed-loop rollouts (IDM ego, shipped evaluation scene
0, seed 0, the shipped checkpoints and every default) of RiskFlow (both targets), the
unguided generator, STRIVE-style and CTG-style, recorded before the planning cycle became
a pipeline of stages (and equal, bit for bit, to the rollouts after it on this machine).
A refactoring that changes an operation's order may move them by float rounding, which a
closed loop amplifies; anything beyond 1 mm is a change of behaviour.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from policies.harness import ClosedLoop
from policies.planners import IDMPlanner
from policies.registry import build_policy
from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import shipped_bank

pytestmark = pytest.mark.integration

EXPECTED = np.load(Path(__file__).with_name("default_rollouts.npz"))
TOLERANCE = 1e-3  # [m, m/s, rad]


@pytest.mark.parametrize("key", sorted(EXPECTED.files))
def test_default_rollouts_are_unchanged(key):
    method, target = key.split("/")
    threads = torch.get_num_threads()
    policy = build_policy(method, {}, k=5, planning_interval=0.5, target=target, seed=0)
    try:
        with ClosedLoop(IDMPlanner(), policy, config=EnvConfig(episode_steps=20)) as loop:
            record = loop.run(shipped_bank("eval")[0], seed=0)
    finally:
        torch.set_num_threads(threads)
    expected = EXPECTED[key]
    assert record.states.shape == expected.shape
    np.testing.assert_allclose(
        record.states, expected, rtol=0, atol=TOLERANCE, equal_nan=True, err_msg=key
    )
