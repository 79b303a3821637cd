"""The multi-agent path: learned adversaries (SuperSuit parameter sharing + SB3 PPO) against
a fixed ego. Needs the ``rl`` extra; skipped with the reason without it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip(
    "stable_baselines3", reason="stable-baselines3 is not installed (pip install -e '.[rl]')"
)
pytest.importorskip("supersuit", reason="supersuit is not installed (pip install -e '.[rl]')")

from policies.planners import ConstantVelocityPlanner  # noqa: E402
from policies.rl.marl import (  # noqa: E402
    FixedEgoParallelEnv,
    FullRosterSource,
    full_roster_env,
    marl_vec_env,
    rollout_ego_collisions,
)

ROOT = Path(__file__).resolve().parents[2]
SLOTS = 4


def test_full_roster_scenes_fill_every_slot():
    # env seed 262 draws a highway scene with 5 of 6 vehicles first (place_traffic drops
    # overlapping candidates); SuperSuit's vector env would fail on its empty slot
    env = full_roster_env(6, episode_steps=5)
    for seed in (0, 262):
        observations, _ = env.reset(seed=seed)
        assert len(observations) == 6
    with pytest.raises(RuntimeError, match="no highway scene with 60 vehicles"):
        FullRosterSource(60, attempts=2).sample(np.random.default_rng(0), 60)


def test_fixed_ego_env_hides_the_ego_and_rewards_adversaries():
    env = FixedEgoParallelEnv(full_roster_env(SLOTS, episode_steps=5), ConstantVelocityPlanner())
    observations, _ = env.reset(seed=0)
    assert "ego" not in env.possible_agents and sorted(observations) == sorted(env.agents)
    assert len(env.agents) == SLOTS - 1
    steps = 0
    while env.agents:
        actions = {agent: np.zeros(2) for agent in env.agents}
        observations, rewards, terminations, truncations, infos = env.step(actions)
        steps += 1
        assert "ego" not in rewards and set(rewards) == set(infos)
        for agent, info in infos.items():
            assert rewards[agent] == pytest.approx(sum(info["adversary_terms"].values()))
    assert steps == 5 and all(truncations.values())
    assert env.env.scene.current[0, 2] > 0  # the fixed ego drove on


def test_parameter_sharing_vec_env_trains_with_ppo():
    from stable_baselines3 import PPO

    vec_env = marl_vec_env(slots=SLOTS, num_envs=2, episode_steps=8)
    assert vec_env.num_envs == 2 * (SLOTS - 1)  # one row per adversary per scene
    vec_env.seed(0)
    model = PPO("MlpPolicy", vec_env, n_steps=16, batch_size=48, n_epochs=1, seed=0, device="cpu")
    model.learn(96)
    env = FixedEgoParallelEnv(full_roster_env(SLOTS, episode_steps=6))
    hits = rollout_ego_collisions(env, lambda batch: model.predict(batch)[0], episodes=2)
    assert len(hits) == 2 and all(isinstance(hit, bool) for hit in hits)
    vec_env.close()


def test_train_adversaries_example(tmp_path):
    command = [
        sys.executable, str(ROOT / "examples" / "train_adversaries_marl.py"),
        "--total-timesteps", "64", "--slots", "3", "--num-envs", "1", "--episode-steps", "8",
        "--n-steps", "32", "--batch-size", "32", "--eval-episodes", "2", "--out", tmp_path,
    ]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    results = json.loads((tmp_path / "results.json").read_text())
    assert set(results) == {"untrained", "trained"} and results["trained"]["n"] == 2
    assert (tmp_path / "model.zip").is_file() and "adversaries hit the ego" in done.stdout
