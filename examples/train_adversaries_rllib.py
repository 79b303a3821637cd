"""Learned adversaries with RLlib PPO (new API stack): one shared policy for every vehicle
but a fixed IDM ego.

    python examples/train_adversaries_rllib.py --iterations 20 --num-env-runners 2 \\
        --out runs/adversaries_rllib

The RLlib counterpart of ``train_adversaries_marl.py`` (SuperSuit + SB3): the same env
(:class:`policies.rl.marl.FixedEgoParallelEnv`, adversary reward, full-roster highway
scenes, nobody finishes early) in RLlib's ``ParallelPettingZooEnv``, every adversary
mapped to the policy ``shared`` (parameter sharing). ``--num-env-runners N`` samples in N
Ray actors; ``--address`` joins a Ray cluster. Prints, per iteration, the env steps
sampled, env steps per second and the mean episode return (summed over the adversaries);
writes ``<out>/checkpoint`` and ``<out>/progress.json``.
"""

from __future__ import annotations

from dataclasses import dataclass

from policies.dataclass_cli import parse_dataclass
from policies.rl.rllib import RLlibOptions, adversaries_env, build_ppo, train
from riskflow_env.cli_errors import require_extra


@dataclass(frozen=True)
class Options(RLlibOptions):
    """Options of train_adversaries_rllib.py."""

    slots: int = 6
    """vehicles per scene, the ego included (slots - 1 learned adversaries)"""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.slots < 2:
            raise ValueError("--slots must be >= 2 (the ego and at least one adversary)")


def main(argv: list[str] | None = None) -> None:
    options = parse_dataclass(Options, argv, prog="train_adversaries_rllib.py", description=__doc__)
    env_config = {"slots": options.slots, "episode_steps": options.episode_steps}
    adversaries = [f"agent_{i}" for i in range(1, options.slots)]
    train(build_ppo(adversaries_env, env_config, {"shared": adversaries}, options), options)


if __name__ == "__main__":
    require_extra("train_adversaries_rllib.py", "rllib", "ray.rllib")
    main()
