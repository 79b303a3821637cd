"""Batched planning equals planning each scene alone with what ships: the shipped
checkpoint and every default of RiskFlow (the realistic base, ``L_sep``), four shipped
scenes of different sizes, ten planning cycles, the same views for both (the scenes driven
by the one-scene policies' actions).

The network outputs of a scene in a batch are those it gets alone, bit for bit (planning
groups the scenes' social attention by exact width, ``policies.learned.packing``), and so
is every stage after it, each row computed from its own inputs only (the rollout's
gradient picks its speed-bound path row by row, ``riskflow_env.dynamics``): the plans
are equal bit for bit on the CPUs measured. The tolerance is for a BLAS whose rounding
depends on the matrix's shape (MKL with ``MKL_CBWR=COMPATIBLE`` and scalar ATen kernels
gives 1e-6 differences in the generator's output, which the guidance's Adam steps
amplify to 3.5e-3 m by cycle 10).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from policies.pipeline.batched import BatchedAdversary
from policies.riskflow import RiskFlowAdversary
from riskflow_env.env import RiskFlowParallelEnv
from riskflow_env.scenarios import shipped_bank

pytestmark = pytest.mark.integration

SCENES = (0, 1, 2, 3)  # 11, 11, 27 and 23 vehicles in their windows
CYCLES = 10
TOLERANCE = 1e-3  # [m]


def test_batched_plans_equal_each_scene_alone_with_the_shipped_defaults():
    threads = torch.get_num_threads()
    bank = shipped_bank("eval")
    envs = []
    for index in SCENES:
        env = RiskFlowParallelEnv(scenarios=bank[index])
        env.reset(seed=0, options={"scenario": bank[index]})
        envs.append(env)
    seeds = list(range(len(SCENES)))
    batch = BatchedAdversary(RiskFlowAdversary(), len(SCENES), seeds=seeds)
    alone = [RiskFlowAdversary(seed=seed) for seed in seeds]
    try:
        batch.reset([env.view() for env in envs])
        for policy, env in zip(alone, envs, strict=True):
            policy.reset(env.view())
        cycles = 0
        for _ in range(CYCLES * alone[0].interval_steps):
            views = [env.view() for env in envs]
            expected = [policy.act(view) for policy, view in zip(alone, views, strict=True)]
            batch.act(views)
            if batch.last_planned:
                cycles += 1
                for mine, theirs in zip(batch.scenes, alone, strict=True):
                    assert torch.equal(mine.noise, theirs.noise)
                    np.testing.assert_array_equal(mine.controllable, theirs.controllable)
                    np.testing.assert_allclose(
                        mine.plans[..., :2], theirs.plans[..., :2], rtol=0, atol=TOLERANCE,
                        equal_nan=True, err_msg=f"cycle {cycles}",
                    )  # fmt: skip
            for env, actions in zip(envs, expected, strict=True):
                env.step(dict(actions) | ({"ego": np.zeros(2)} if "ego" in env.agents else {}))
    finally:
        torch.set_num_threads(threads)
    assert cycles == CYCLES
