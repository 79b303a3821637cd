"""TorchRL's ``PettingZooWrapper`` over ``FixedRosterEnv``: ``check_env_specs``, the mask of
padded slots in the tensordict, and actions for every slot (the ``torchrl`` extra)."""

from __future__ import annotations

import pytest
import torch

from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import HighwayTrafficSource, TrafficConfig
from riskflow_env.wrappers import FixedRosterEnv

pytestmark = pytest.mark.extras
torchrl_pettingzoo = pytest.importorskip(
    "torchrl.envs.libs.pettingzoo",
    reason="torchrl is not installed (pip install -e '.[torchrl]'; .ci/run installs it)",
)
from torchrl.envs.utils import check_env_specs  # noqa: E402

SLOTS = 5
FEW = HighwayTrafficSource(TrafficConfig(families=("highway",), num_vehicles=(2, 4)))


def make_env(seed: int = 0):
    env = FixedRosterEnv(config=EnvConfig(max_agents=SLOTS, episode_steps=6), scenarios=FEW)
    return torchrl_pettingzoo.PettingZooWrapper(env, seed=seed)


def test_check_env_specs():
    check_env_specs(make_env())


def test_rollout_masks_padded_slots_and_resets_after_the_episode():
    env = make_env()
    assert env.group_map == {"ego": ["ego"], "agent": [f"agent_{i}" for i in range(1, SLOTS)]}
    rollout = env.rollout(14, break_when_any_done=False)  # 6-step episodes, reset twice
    live = rollout["next", "agent", "info", "live"].bool()
    observation = rollout["next", "agent", "observation"]
    reward = rollout["next", "agent", "reward"].squeeze(-1)
    assert not live.all() and rollout["next", "ego", "info", "live"].bool().all()
    assert not observation[~live].any() and not reward[~live].any()
    assert observation[live].abs().sum(-1).gt(0).all()
    assert rollout["next", "done"].squeeze(-1).tolist().count(True) == 2
    assert rollout["next", "agent", "info", "reward_terms"].shape == (14, SLOTS - 1, 5)


def test_same_seed_same_rollout():
    torch.manual_seed(0)
    first = make_env(seed=1).rollout(8, break_when_any_done=False)
    torch.manual_seed(0)
    second = make_env(seed=1).rollout(8, break_when_any_done=False)
    assert torch.equal(
        first["next", "agent", "observation"], second["next", "agent", "observation"]
    )
    assert torch.equal(first["agent", "action"], second["agent", "action"])
