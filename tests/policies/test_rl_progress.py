"""The tqdm bar of the PPO examples counts environment steps up to the total."""

from __future__ import annotations

import pytest

pytest.importorskip("stable_baselines3", reason="the rl extra is not installed")


def test_step_progress_bar_reaches_the_total():
    import gymnasium as gym
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    from policies.rl.progress import StepProgressBar

    env = make_vec_env(lambda: gym.make("CartPole-v1"), n_envs=2, seed=0)
    model = PPO("MlpPolicy", env, n_steps=32, batch_size=32, n_epochs=1, seed=0, device="cpu")
    bar = StepProgressBar(64, "test")
    model.learn(64, callback=bar)
    assert bar.bar.total == 64 and bar.bar.n == model.num_timesteps == 64


def test_step_progress_bar_ends_at_the_whole_rollout_learn_runs():
    """A total that is not a whole number of rollouts: learn() runs on to the end of the
    rollout that passes it, and the bar's total says so (it overran 100 before)."""
    import gymnasium as gym
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    from policies.rl.progress import StepProgressBar

    env = make_vec_env(lambda: gym.make("CartPole-v1"), n_envs=2, seed=0)
    model = PPO("MlpPolicy", env, n_steps=32, batch_size=32, n_epochs=1, seed=0, device="cpu")
    bar = StepProgressBar(100, "test")
    model.learn(100, callback=bar)
    assert bar.bar.total == bar.bar.n == model.num_timesteps == 128
