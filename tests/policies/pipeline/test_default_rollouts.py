"""The shipped methods' default rollouts stay what they were.

``default_rollouts.npz`` holds 2 s closed-loop rollouts (IDM ego, shipped evaluation scene
0, seed 0, the shipped checkpoints and every default) of RiskFlow (both targets), the
unguided generator, STRIVE-style and CTG-style, recorded before the planning cycle became
a pipeline of stages (and equal, bit for bit, to the rollouts after it on this machine);
``riskflow/ego`` re-recorded, the same way, when target ``"ego"`` became one attacker at a
time (``policies.learned.ranking.ego_attacker``), again when its separation term began
to keep the attacker clear of the bystanders (``policies.learned.plan_overlap``), and
when its guidance horizon became 3 s and its braking was bounded by the human p99
(``policies.learned.guidance_losses.HORIZONS``, ``HUMAN_ACCEL``), when the attacker
was kept moving (``KEEP_MOVING``), and when the map term began to score the guidance
horizon only and the attacker's yaw rate was bounded by the human p99 (``HUMAN_YAW_RATE``).
A refactoring that changes an operation's order may move them by float rounding, which a
closed loop amplifies; anything beyond 1 mm is a change of behaviour.

CTG-style is pinned unguided (``ctg/unguided``: K = 0, the diffusion chain, its stitching
and holding at rest). Its guided rows are not portable: each guidance step has a fixed
length whatever the gradient's size (``policies.baselines.diffusion.guided``), so the
float32 rounding of a CPU's kernels (MKL takes other code paths on AMD than on Intel)
moves the guided plans by metres within one planning cycle; its guidance has tests of
its own (``tests/policies/baselines/test_diffusion_policy.py``). ``python -m
tests.policies.pipeline.test_default_rollouts [KEY ...]`` re-records the named rollouts (all
without a key) and keeps the others, only for a deliberate change of behaviour.
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

PATH = Path(__file__).with_name("default_rollouts.npz")
EXPECTED = np.load(PATH)
TOLERANCE = 1e-3  # [m, m/s, rad]


def rollout(key: str):
    """The record of the 2 s default rollout of ``key``: ``"method/target"`` (K = 5) or
    ``"method/unguided"`` (K = 0)."""
    method, target = key.split("/")
    k, target = (0, "others") if target == "unguided" else (5, target)
    threads = torch.get_num_threads()
    policy = build_policy(method, {}, k=k, planning_interval=0.5, target=target, seed=0)
    try:
        with ClosedLoop(IDMPlanner(), policy, config=EnvConfig(episode_steps=20)) as loop:
            return loop.run(shipped_bank("eval")[0], seed=0)
    finally:
        torch.set_num_threads(threads)


@pytest.mark.parametrize("key", sorted(EXPECTED.files))
def test_default_rollouts_are_unchanged(key):
    record = rollout(key)
    expected = EXPECTED[key]
    assert record.states.shape == expected.shape
    np.testing.assert_allclose(
        record.states, expected, rtol=0, atol=TOLERANCE, equal_nan=True, err_msg=key
    )


if __name__ == "__main__":
    import sys

    keys = sys.argv[1:] or EXPECTED.files
    unknown = sorted(set(keys) - set(EXPECTED.files))
    if unknown:
        raise SystemExit(f"unknown rollouts {unknown}; the file holds {EXPECTED.files}")
    rollouts = {
        key: rollout(key).states if key in keys else EXPECTED[key] for key in EXPECTED.files
    }
    np.savez_compressed(PATH, **rollouts)
