"""RLlib PPO (new API stack) on ``riskflow_v0``: what the two RLlib example scripts share.

The env goes to RLlib as a name registered with ``ray.tune.registry.register_env`` whose
creator wraps a PettingZoo ``ParallelEnv`` with fixed agents (every agent live until the
episode ends for all) in RLlib's own ``ParallelPettingZooEnv``: no wrapper of our own.
``num_env_runners`` = 0 samples in the driver; N > 0 samples in N Ray actors (each a copy
of the env, one CPU), on the local Ray instance or the cluster given to ``ray.init``.
The algorithm is saved to ``<out>/checkpoint`` every ``checkpoint_every`` iterations, at
the end and on Ctrl-C / SIGTERM; ``resume`` restores it (RLlib's ``restore_from_path``:
weights, optimiser, counters) and goes on; the episodes in flight start afresh.
Needs the ``rllib`` extra.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from policies.dataclass_cli import check_at_least, check_field_types
from policies.rl.runs import check_resume
from policies.rl.signals import StopSignals, exit_stopped
from riskflow_env.atomic_files import write_text

CHECKPOINT = "checkpoint"  # <out>/checkpoint: the algorithm (RLlib's save_to_path)


@dataclass(frozen=True)
class RLlibOptions:
    """Options every RLlib example shares."""

    iterations: int = 20
    """PPO training iterations (each samples --train-batch env steps per agent group)"""
    seed: int = 0
    """seeds RLlib (torch, numpy, the env runners' envs)"""
    num_env_runners: int = 0
    """Ray actors that sample (0: sample in this process)"""
    num_cpus: int = 2
    """CPUs of the local Ray instance (ignored with --address)"""
    address: str | None = None
    """Ray cluster to join ('auto', 'ray://host:10001'); default: a local Ray"""
    episode_steps: int = 100
    """episode length [steps of 0.1 s]"""
    train_batch: int = 2000
    """env steps per training iteration (train_batch_size_per_learner)"""
    minibatch: int = 500
    """PPO minibatch size"""
    epochs: int = 4
    """PPO epochs per iteration"""
    out: Path = Path("runs/rllib")
    """output folder (checkpoint, progress.json)"""
    checkpoint_every: int = 5
    """write <out>/checkpoint and <out>/progress.json every N iterations (0: only at the end
    and on Ctrl-C / SIGTERM, which always write them)"""
    resume: bool = False
    """continue the run in --out from its checkpoint and progress.json, up to --iterations"""

    def __post_init__(self) -> None:
        check_field_types(self)
        counts = ("iterations", "episode_steps", "train_batch", "minibatch", "epochs")
        check_at_least(
            self, dict.fromkeys(counts, 1) | {"num_env_runners": 0, "checkpoint_every": 0}
        )
        if self.minibatch > self.train_batch:
            raise ValueError("--minibatch must be <= --train-batch")
        check_resume(Path(self.out) / CHECKPOINT, self.resume)


def ego_vs_riskflow_env(env_config: Mapping[str, Any]):
    """RLlib env creator: the ego learns (the only agent), the RiskFlow adversary drives the
    others (``FixedRosterEnv(roster=["ego"])``). ``env_config``: ``max_agents``,
    ``episode_steps``, ``k``, ``guidance_steps``, ``planning_interval`` [s], ``seed``."""
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

    from policies.riskflow import RiskFlowAdversary
    from riskflow_env.config import EnvConfig
    from riskflow_env.wrappers import FixedRosterEnv

    adversary = RiskFlowAdversary(
        k=env_config["k"],
        planning_interval=env_config["planning_interval"],
        guidance_steps=env_config["guidance_steps"],
        seed=env_config["seed"],
    )
    config = EnvConfig(
        max_agents=env_config["max_agents"], episode_steps=env_config["episode_steps"]
    )
    return ParallelPettingZooEnv(FixedRosterEnv(config=config, policy=adversary, roster=["ego"]))


def adversaries_env(env_config: Mapping[str, Any]):
    """RLlib env creator: every vehicle but the ego learns, with the adversary reward, against
    a fixed IDM ego (:class:`~policies.rl.marl.FixedEgoParallelEnv` on full-roster highway
    scenes in which nobody finishes early). ``env_config``: ``slots``, ``episode_steps``."""
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

    from policies.rl.marl import FixedEgoParallelEnv, full_roster_env

    env = full_roster_env(env_config["slots"], env_config["episode_steps"])
    return ParallelPettingZooEnv(FixedEgoParallelEnv(env))


def build_ppo(
    make_env: Callable[[Mapping[str, Any]], Any],
    env_config: dict[str, Any],
    policies: dict[str, list[str]],
    options: RLlibOptions,
):
    """A PPO algorithm on the env ``make_env(env_config)``.

    Args:
        make_env: ``env_config -> ParallelPettingZooEnv``, importable (env runners call it).
        env_config: its argument.
        policies: ``{policy id: agent ids it acts for}``; one shared policy for many agents
            is parameter sharing.
        options: training options.
    """
    import ray
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.tune.registry import register_env

    if not ray.is_initialized():
        if options.address is None:
            ray.init(num_cpus=options.num_cpus, include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=options.address, log_to_driver=False)
    name = f"riskflow_{make_env.__name__}"
    register_env(name, make_env)
    policy_of = {agent: policy for policy, agents in policies.items() for agent in agents}
    fragment = max(1, options.train_batch // max(1, options.num_env_runners))
    config = (
        PPOConfig()
        .environment(name, env_config=env_config)
        .env_runners(num_env_runners=options.num_env_runners, rollout_fragment_length=fragment)
        .multi_agent(
            policies=set(policies),
            policy_mapping_fn=lambda agent_id, *_, **__: policy_of[agent_id],
        )
        .training(
            train_batch_size_per_learner=options.train_batch,
            minibatch_size=options.minibatch,
            num_epochs=options.epochs,
        )
        .debugging(seed=options.seed)
    )
    return config.build_algo()


def train(algorithm, options: RLlibOptions) -> list[dict[str, float]]:
    """``algorithm`` trained (:func:`_iterations`), then stopped, also on an error. On
    SIGINT / SIGTERM it saves after the iteration under way and exits with one line
    (status 130 / 143)."""
    with StopSignals() as stop:
        try:
            history = _iterations(algorithm, options, stop)
        finally:
            algorithm.stop()
    if stop.received is not None:
        exit_stopped(
            stop.received,
            f"stopped by {{name}} after iteration {len(history)}; checkpoint "
            f"{options.out / CHECKPOINT}; continue with --resume --out {options.out}",
        )
    return history


def _iterations(algorithm, options: RLlibOptions, stop: StopSignals) -> list[dict[str, float]]:
    """Run PPO iterations up to ``options.iterations`` (with ``resume``, from the saved
    ones on); per iteration: env steps sampled so far, wall time [s], env steps per second
    of the whole iteration (sampling and learning) and the mean episode return, printed
    and written to ``<out>/progress.json`` with the algorithm in ``<out>/checkpoint``
    every ``checkpoint_every`` iterations, at the end and on a stop signal."""
    out = options.out
    history: list[dict[str, float]] = []
    if options.resume:
        algorithm.restore_from_path(str((out / CHECKPOINT).resolve()))
        history = json.loads((out / "progress.json").read_text())
        print(f"resuming {out} after iteration {len(history)}")
    steps_before = history[-1]["env_steps"] if history else 0.0
    saved = len(history)
    for iteration in tqdm(range(len(history), options.iterations), desc="PPO iterations",
                          unit="it", initial=len(history), total=options.iterations):  # fmt: skip
        start = time.perf_counter()
        result = algorithm.train()
        wall = time.perf_counter() - start
        runners = result["env_runners"]
        steps = float(runners["num_env_steps_sampled_lifetime"])
        row = {
            "iteration": iteration + 1,
            "env_steps": steps,
            "wall_s": wall,
            "env_steps_per_s": (steps - steps_before) / wall,
            "episode_return_mean": float(runners.get("episode_return_mean", float("nan"))),
        }
        history.append(row)
        print(
            f"iteration {row['iteration']}: {row['env_steps']:.0f} env steps, "
            f"{row['env_steps_per_s']:.0f} env steps/s, return {row['episode_return_mean']:.2f}"
        )
        steps_before = steps
        every = options.checkpoint_every
        if stop.received is not None or (every and (iteration + 1) % every == 0):
            _save(algorithm, out, history)
            saved = len(history)
        if stop.received is not None:
            break
    if saved != len(history) or not (out / CHECKPOINT).is_dir():
        _save(algorithm, out, history)
    return history


def _save(algorithm, out: Path, history: list[dict[str, float]]) -> None:
    """The algorithm in ``<out>/checkpoint`` and the rows so far in ``<out>/progress.json``."""
    out.mkdir(parents=True, exist_ok=True)
    algorithm.save_to_path(str((out / CHECKPOINT).resolve()))
    write_text(out / "progress.json", json.dumps(history, indent=1))
