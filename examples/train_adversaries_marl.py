"""Learned RL adversaries against a fixed IDM ego: SuperSuit parameter sharing + SB3 PPO.

    python examples/train_adversaries_marl.py --total-timesteps 200000 --out runs/marl_adversaries

The counterpart of the generative RiskFlow adversary: here the other vehicles are RL
agents of ``riskflow_v0`` sharing one PPO policy (SuperSuit turns each agent of each
scene into one row of an SB3 vector env), rewarded for closing in on and colliding with
the ego, punished for collisions among themselves and for leaving the road
(:class:`policies.rl.marl.AdversaryRewardConfig`); the ego is a fixed IDM planner.
Scenes: highway-env highway traffic that fills every slot (SuperSuit's plain conversion
needs every agent at every step; see :mod:`policies.rl.marl`).

Before and after training it runs ``--eval-episodes`` episodes and prints the share in
which an adversary hit the ego (Wilson 95% interval), untrained policy vs trained.
Writes ``<out>/options.json``, ``<out>/model.zip``, ``<out>/progress.csv`` and
``<out>/results.json``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import configure
from stable_baselines3.common.utils import set_random_seed

from policies.dataclass_cli import check_at_least, check_between, parse_dataclass
from policies.rl.marl import (
    AdversaryRewardConfig,
    FixedEgoParallelEnv,
    full_roster_env,
    marl_vec_env,
    rollout_ego_collisions,
)
from policies.rl.progress import StepProgressBar
from policies.rl.signals import StopSignals, exit_stopped
from policies.statistics import wilson_interval
from riskflow_env.cli_errors import debug_requested, user_errors
from riskflow_env.folder_lock import check_output_folder

PROG = "train_adversaries_marl.py"
MAX_SLOTS = 20  # [vehicles] highway-env's highway holds 20 without a failed draw


@dataclass(frozen=True)
class Options:
    """Options of train_adversaries_marl.py."""

    total_timesteps: int = 200_000
    """agent-steps to train for (every adversary's step counts)"""
    seed: int = 0
    """seeds PPO, torch, numpy and the scene draws"""
    out: Path = Path("runs/marl_adversaries")
    """output folder"""
    slots: int = 6
    """vehicles per scene, the ego included (slots - 1 learned adversaries)"""
    num_envs: int = 2
    """scenes stepped together"""
    episode_steps: int = 100
    """episode length [steps of 0.1 s]"""
    n_steps: int = 256
    """PPO rollout length per vector-env row"""
    batch_size: int = 256
    """PPO minibatch size"""
    ego_collision_reward: float = 5.0
    """adversary reward while overlapping the ego [per step]"""
    closeness_reward: float = 0.05
    """weight of the closeness-to-ego shaping term [per step]"""
    eval_episodes: int = 10
    """episodes of the before / after evaluation"""

    def __post_init__(self) -> None:
        counts = ("total_timesteps", "num_envs", "episode_steps", "eval_episodes")
        lows = dict.fromkeys(counts, 1) | {"seed": 0, "slots": 2, "n_steps": 2, "batch_size": 2}
        check_at_least(self, lows, highs={"seed": 2**32 - 1, "slots": MAX_SLOTS})
        rewards = ("ego_collision_reward", "closeness_reward")
        check_between(self, dict.fromkeys(rewards, (-math.inf, math.inf)))
        check_output_folder(self.out, "--out")


def ego_hit_rate(model: PPO, options: Options, reward: AdversaryRewardConfig) -> dict:
    """Share of evaluation episodes in which an adversary hit the ego, with its interval."""
    env = FixedEgoParallelEnv(full_roster_env(options.slots, options.episode_steps), None, reward)
    hits = rollout_ego_collisions(
        env,
        lambda batch: model.predict(batch, deterministic=True)[0],
        options.eval_episodes,
        seed=10_000 + options.seed,  # scenes unseen in training
    )
    low, high = wilson_interval(sum(hits), len(hits))
    return {"ego_hit_rate": sum(hits) / len(hits), "low": low, "high": high, "n": len(hits)}


def main(argv: list[str] | None = None) -> None:
    options = parse_dataclass(Options, argv, prog=PROG, description=__doc__, debug=True)
    with user_errors(PROG, debug_requested(argv or sys.argv[1:])):
        train(options)


def train(options: Options) -> None:
    """Evaluate, train, save and evaluate again; Ctrl-C or SIGTERM during training saves
    the model as trained so far and skips the second evaluation."""
    out = options.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "options.json").write_text(json.dumps(dataclasses.asdict(options), default=str))
    set_random_seed(options.seed)
    reward = AdversaryRewardConfig(
        ego_collision=options.ego_collision_reward, closeness=options.closeness_reward
    )
    vec_env = marl_vec_env(options.slots, options.num_envs, options.episode_steps, reward=reward)
    vec_env.seed(options.seed)
    model = PPO(
        "MlpPolicy",
        vec_env,
        n_steps=options.n_steps,
        batch_size=options.batch_size,
        seed=options.seed,
        device="cpu",
        verbose=0,
    )
    model.set_logger(configure(str(out), ["csv", "stdout"]))
    before = ego_hit_rate(model, options, reward)
    with StopSignals() as stop:
        bar = StepProgressBar(options.total_timesteps, "PPO")
        model.learn(options.total_timesteps, callback=[bar, StopOn(stop)])
    model.save(out / "model")
    vec_env.close()
    if stop.received is not None:
        exit_stopped(
            stop.received,
            f"{PROG}: stopped by {{name}} after {model.num_timesteps} agent-steps; "
            f"the model so far is {out / 'model.zip'} (not evaluated)",
        )
    after = ego_hit_rate(model, options, reward)
    results = {"untrained": before, "trained": after}
    (out / "results.json").write_text(json.dumps(results, indent=1))
    for name, result in results.items():
        print(
            f"{name}: adversaries hit the ego in {result['ego_hit_rate']:.2f} "
            f"[{result['low']:.2f}, {result['high']:.2f}] of {result['n']} episodes"
        )


class StopOn(BaseCallback):
    """Ends ``learn`` at the next step once ``stop`` received a signal."""

    def __init__(self, stop: StopSignals) -> None:
        super().__init__()
        self.stop = stop

    def _on_step(self) -> bool:
        return self.stop.received is None


if __name__ == "__main__":
    main()
