"""An ego trained with RLlib PPO (new API stack) against the RiskFlow adversary.

    python examples/train_ego_rllib.py --iterations 20 --num-env-runners 2 --out runs/ego_rllib

The ego is the only agent of ``FixedRosterEnv(roster=["ego"], policy=RiskFlowAdversary)``
on the shipped scenes, handed to RLlib as ``ParallelPettingZooEnv`` (no wrapper of our
own); the adversary (``--k`` guided vehicles, ``--guidance-steps`` per plan) drives every
other vehicle. ``--num-env-runners N`` samples in N Ray actors; ``--address`` joins a Ray
cluster. Prints, per iteration, the env steps sampled, env steps per second and the mean
episode return; writes ``<out>/checkpoint`` and ``<out>/progress.json`` every
``--checkpoint-every`` iterations (5), at the end and on Ctrl-C / SIGTERM (one line, status
130 / 143); ``--resume`` goes on from them up to ``--iterations``:

    python examples/train_ego_rllib.py --iterations 40 --resume --out runs/ego_rllib
"""

from __future__ import annotations

from dataclasses import dataclass

from policies.dataclass_cli import parse_dataclass
from policies.rl.rllib import RLlibOptions, build_ppo, ego_vs_riskflow_env, train
from riskflow_env.cli_errors import require_extra


@dataclass(frozen=True)
class Options(RLlibOptions):
    """Options of train_ego_rllib.py."""

    max_agents: int = 16
    """vehicle slots per scene, the ego included"""
    k: int = 3
    """vehicles the adversary guides toward a collision"""
    guidance_steps: int = 10
    """guidance gradient steps per plan (the default adversary: 30)"""
    planning_interval: float = 1.0
    """[s] re-planning interval of the adversary"""


def main(argv: list[str] | None = None) -> None:
    options = parse_dataclass(Options, argv, prog="train_ego_rllib.py", description=__doc__)
    env_config = {
        "max_agents": options.max_agents,
        "episode_steps": options.episode_steps,
        "k": options.k,
        "guidance_steps": options.guidance_steps,
        "planning_interval": options.planning_interval,
        "seed": options.seed,
    }
    train(build_ppo(ego_vs_riskflow_env, env_config, {"ego": ["ego"]}, options), options)


if __name__ == "__main__":
    require_extra("train_ego_rllib.py", "rllib", "ray.rllib")
    main()
