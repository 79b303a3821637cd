"""What users of RL libraries expect of ``RiskFlowEgo-v0`` (issue 55): ``gymnasium.make_vec``
returns the batched vector env with the single env's spaces, observation spaces are bounded
where physical bounds exist, and maneuver actions come with an action mask in ``info``."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import gymnasium
import numpy as np
import pytest

import riskflow_env  # noqa: F401 - registers RiskFlowEgo-v0
from policies.rl.envs import EgoTrainingEnv
from policies.rl.features import maneuvers
from policies.rl.vector_env import EgoVectorEnv
from riskflow_env.config import EnvConfig
from riskflow_env.wrappers import EgoEnv
from tests.policies.straight_road import make_road_scenario
from tests.policies.straight_scenes import make_scenario

CONFIG = EnvConfig(episode_steps=6)


def test_make_vec_returns_the_batched_vector_env_with_the_single_envs_spaces():
    scenes = [make_scenario(i) for i in range(3)]
    vector = gymnasium.make_vec(
        "RiskFlowEgo-v0", num_envs=2, vectorization_mode="vector_entry_point",
        config=CONFIG, scenarios=scenes,
    )  # fmt: skip
    assert isinstance(vector, EgoVectorEnv) and vector.num_envs == 2
    assert gymnasium.make_vec("RiskFlowEgo-v0", num_envs=2, config=CONFIG).__class__ is EgoVectorEnv
    single = gymnasium.make("RiskFlowEgo-v0", config=CONFIG, scenarios=scenes)
    assert vector.single_observation_space == single.observation_space
    assert vector.single_action_space == single.action_space  # (accel [m/s^2], yaw rate [rad/s])
    observations, _ = vector.reset(seed=5)
    actions = np.array([[1.5, 0.1], [-3.0, -0.2]])
    stepped = [vector.step(actions)[0] for _ in range(3)]
    for b in range(2):  # scene b is the single env reset with seed 5 + b, given the same actions
        observation, _ = single.reset(seed=5 + b)
        np.testing.assert_allclose(observations[b], observation, atol=1e-4)
        for row in stepped:
            observation = single.step(actions[b].astype(np.float32))[0]
            np.testing.assert_allclose(row[b], observation, atol=1e-4)
    with pytest.raises(ValueError, match="render_mode must be None for the vector env"):
        gymnasium.make_vec("RiskFlowEgo-v0", num_envs=2, render_mode="rgb_array")


def test_observations_lie_in_their_bounded_space():
    env = EgoTrainingEnv(EgoEnv(config=CONFIG, scenarios=[make_scenario(i) for i in range(3)]),
                         maneuver_features=True)  # fmt: skip
    space = env.observation_space
    np.testing.assert_array_equal(space.low[:6], [0.0, -8.0, -1.0, 0.0, 0.0, -np.inf])
    np.testing.assert_array_equal(space.high[:3], [np.inf, 5.0, 1.0])  # speed, last action
    neighbour = space.low[6:17], space.high[6:17]  # dx, dy, cos, sin, dvx, dvy, d, risk, l, w, p
    np.testing.assert_array_equal(neighbour[0], [-50, -50, -1, -1, -np.inf, -np.inf, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(neighbour[1][[0, 1, 2, 3, 7, 10]], [50, 50, 1, 1, 1, 1])
    assert (space.low[-30:] == -10).all() and (space.high[-30:] == 10).all()  # the features
    rng = np.random.default_rng(0)
    for seed in range(3):
        observation, _ = env.reset(seed=seed)
        assert space.contains(observation)
        for _ in range(5):
            observation, *_ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
            assert space.contains(observation)


def edge_scenario(y: float):
    """The straight road (12 m wide, edges at y = +-6 m) with the ego at lateral ``y``."""
    scenario = make_road_scenario()
    states = scenario.states.copy()
    states[0, :, 1] = y
    return dataclasses.replace(scenario, states=states)


def test_the_action_mask_removes_maneuvers_that_leave_the_road_within_a_second():
    """Ego 0.4 m from the left edge at 12 m/s: turning or changing lane to the left leaves
    the road within 1 s, so those are masked; the rest stay available."""
    env = EgoTrainingEnv(EgoEnv(config=CONFIG, scenarios=edge_scenario(4.6)), maneuver_actions=True)
    _, info = env.reset(seed=0)
    mask = info["action_mask"]
    left = maneuvers()[:, 0, 1] > 0  # yaw rate to the left at the start
    assert mask.dtype == bool and mask.shape == (15,)
    assert not mask[left].any() and mask[~left].all()
    np.testing.assert_array_equal(env.action_masks(), mask)
    info = env.step(int(np.flatnonzero(mask)[0]))[-1]
    assert info["action_mask"].shape == (15,)
    centred = EgoTrainingEnv(
        EgoEnv(config=CONFIG, scenarios=edge_scenario(0.0)), maneuver_actions=True
    )
    assert centred.reset(seed=0)[1]["action_mask"].all()  # mid-road: every maneuver
    continuous = EgoTrainingEnv(EgoEnv(config=CONFIG, scenarios=edge_scenario(0.0)))
    assert "action_mask" not in continuous.reset(seed=0)[1]


def test_the_ppo_planner_chooses_among_the_maneuvers_the_mask_allows():
    """Ego at the left edge, a policy whose favourite maneuvers go left: masked, it takes its
    most probable maneuver that stays on the road; ``mask_actions=False`` (the raw policy)
    takes the one it prefers."""
    import torch

    from policies.rl.evaluation import PPOPlanner

    left = maneuvers()[:, 0, 1] > 0
    logits = torch.where(torch.as_tensor(left), 5.0, 0.0) + 0.01 * torch.arange(15.0)

    class Policy:
        @staticmethod
        def obs_to_tensor(observation):
            return torch.as_tensor(observation)[None], True

        @staticmethod
        def get_distribution(observation):
            return SimpleNamespace(
                distribution=torch.distributions.Categorical(logits=logits[None])
            )

    class Model:
        policy = Policy()

        def predict(self, observation, deterministic=True):
            return np.int64(torch.argmax(logits)), None

    env = EgoTrainingEnv(EgoEnv(config=CONFIG, scenarios=edge_scenario(4.6)), maneuver_actions=True)
    observation, info = env.reset(seed=0)
    view = env.unwrapped.parallel_env.view()
    allowed = info["action_mask"]
    best_allowed = int(np.flatnonzero(allowed)[np.argmax(logits.numpy()[allowed])])
    table = maneuvers()
    for mask_actions, chosen in ((True, best_allowed), (False, int(torch.argmax(logits)))):
        planner = PPOPlanner(Model(), maneuver_actions=True, mask_actions=mask_actions)
        planner.reset(view)
        np.testing.assert_allclose(planner(observation, view), table[chosen, 0])
    assert left[int(torch.argmax(logits))] and not left[best_allowed]
    sampled = PPOPlanner(Model(), deterministic=False, maneuver_actions=True)
    sampled.reset(view)
    torch.manual_seed(0)
    for _ in range(20):  # draws from the renormalised probabilities: never a masked one
        assert allowed[int(sampled._masked_choice(observation, allowed))]


def test_the_vector_env_reports_each_scenes_action_mask():
    scenes = [edge_scenario(4.6), edge_scenario(0.0)]
    vector = EgoVectorEnv(2, config=CONFIG, scenarios=scenes, maneuver_actions=True)
    _, infos = vector.reset(seed=0, options=None)
    assert infos["action_mask"].shape == (2, 15) and infos["_action_mask"].all()
    for b in range(2):
        single = EgoTrainingEnv(EgoEnv(config=CONFIG, scenarios=scenes), maneuver_actions=True)
        np.testing.assert_array_equal(
            infos["action_mask"][b], single.reset(seed=b)[1]["action_mask"]
        )
    _, _, _, _, infos = vector.step(np.array([7, 7]))
    assert infos["action_mask"].shape == (2, 15)
