"""The maneuver-scoring policy (policies.rl.scoring): one scorer shared by every maneuver."""

from __future__ import annotations

from types import SimpleNamespace

import gymnasium
import numpy as np
import pytest

pytest.importorskip(
    "stable_baselines3", reason="stable-baselines3 is not installed (pip install -e '.[rl]')"
)
import torch  # noqa: E402
from stable_baselines3 import PPO  # noqa: E402

from policies.rl.features import maneuvers  # noqa: E402
from policies.rl.scoring import ManeuverScoringPolicy, sb3_policy  # noqa: E402

ENV_SIZE = 6
BANDIT = {"n_steps": 128, "batch_size": 64, "n_epochs": 10, "learning_rate": 1e-3, "gamma": 0.0,
          "seed": 0, "device": "cpu"}  # fmt: skip
COUNT = len(maneuvers(maneuver_set="compact"))


class FeatureEnv(gymnasium.Env):
    """Observations ``[env (6), gap (M), edge (M)]``; reward 1 for the maneuver of the
    largest gap, whichever it is."""

    observation_space = gymnasium.spaces.Box(-10, 10, (ENV_SIZE + 2 * COUNT,), np.float32)
    action_space = gymnasium.spaces.Discrete(COUNT)

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.observation = self.observation_space.sample()
        return self.observation, {}

    def step(self, action):
        reward = float(action == widest(self.observation))
        self.observation = self.observation_space.sample()
        return self.observation, reward, False, False, {}


def widest(observation: np.ndarray) -> np.ndarray:
    return np.argmax(observation[..., ENV_SIZE : ENV_SIZE + COUNT], axis=-1)


def model(policy: str = "scoring") -> PPO:
    """PPO on :class:`FeatureEnv`, a bandit (gamma 0) that rewards a rule."""
    kwargs = {"features_extractor_kwargs": {"maneuver_set": "compact"}}
    if policy == "mlp":
        return PPO("MlpPolicy", FeatureEnv(), **BANDIT)
    return PPO(ManeuverScoringPolicy, FeatureEnv(), policy_kwargs=kwargs, **BANDIT)


def logits(ppo: PPO, observations: np.ndarray) -> torch.Tensor:
    """The policy's unnormalised action logits (the scorer's outputs)."""
    with torch.no_grad():
        latent = ppo.policy.extract_features(torch.as_tensor(observations, dtype=torch.float32))
        return ppo.policy.action_net(ppo.policy.mlp_extractor.forward_actor(latent))


def test_a_maneuver_logit_reads_only_its_own_features():
    ppo = model()
    for layer in ppo.policy.features_extractor.scorer[::2]:  # away from the near-zero start
        torch.nn.init.normal_(layer.weight)
    obs = np.random.default_rng(0).uniform(-5, 5, (2, ENV_SIZE + 2 * COUNT)).astype(np.float32)
    changed = obs.copy()
    changed[:, ENV_SIZE + 4] += 3.0  # maneuver 4's gap
    changed[:, ENV_SIZE + COUNT + 4] -= 1.0  # and its road margin
    moved = (logits(ppo, obs) - logits(ppo, changed)).abs() > 1e-6
    assert moved[:, 4].all() and not moved[:, :4].any() and not moved[:, 5:].any()
    changed = obs.copy()
    changed[:, 0] += 2.0  # the env's observation: the context of every maneuver
    assert ((logits(ppo, obs) - logits(ppo, changed)).abs() > 1e-6).all()


def test_untrained_is_near_uniform_and_learns_a_rule_over_maneuver_features(tmp_path):
    """The rewarded maneuver changes every step: the shared scorer learns "the largest gap"
    within a budget in which SB3's MlpPolicy stays near chance."""
    obs = np.stack([FeatureEnv.observation_space.sample() for _ in range(256)])
    chosen = {}
    for policy in ("scoring", "mlp"):
        ppo = model(policy)
        if policy == "scoring":
            assert logits(ppo, obs).softmax(-1).max() < 1.5 / COUNT
        ppo.learn(1024)
        chosen[policy] = logits(ppo, obs).softmax(-1)[np.arange(len(obs)), widest(obs)].mean()
    assert chosen["scoring"] > 2.5 / COUNT and chosen["scoring"] > 2 * chosen["mlp"]
    ppo.save(tmp_path / "model")
    loaded = PPO.load(tmp_path / "model.zip", device="cpu")
    assert torch.equal(logits(loaded, obs), logits(ppo, obs))


def test_sb3_policy_names_the_option_that_does_not_fit():
    options = SimpleNamespace(policy="scoring", maneuver_actions=True, maneuver_features=True,
                              maneuver_set="mpc", log_std_init=-1.2)  # fmt: skip
    policy, kwargs = sb3_policy(options)
    assert policy is ManeuverScoringPolicy
    assert kwargs == {"features_extractor_kwargs": {"maneuver_set": "mpc"}}
    assert sb3_policy(SimpleNamespace(**{**vars(options), "policy": "mlp"})) == ("MlpPolicy", {})
    with pytest.raises(ValueError, match="--policy scoring needs --maneuver-actions"):
        sb3_policy(SimpleNamespace(**{**vars(options), "maneuver_features": False}))
    with pytest.raises(ValueError, match=r"--policy must be one of \('mlp', 'scoring'\)"):
        sb3_policy(SimpleNamespace(**{**vars(options), "policy": "gru"}))
    with pytest.raises(ValueError, match="train with --maneuver-features"):
        PPO(ManeuverScoringPolicy, gymnasium.make("CartPole-v1"),
            policy_kwargs={"features_extractor_kwargs": {"maneuver_set": "compact"}})  # fmt: skip
