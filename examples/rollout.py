"""Run one 10 s closed-loop episode and print what happened.

Until the RiskFlow adversary lands, every vehicle follows a simple scripted plan: the
traffic holds its speed, and the ego speeds up by ``--ego-accel`` for the first seconds,
closing in on whoever is ahead. The printout lists every collision and off-road event.

    python examples/rollout.py --seed 3
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np

import riskflow_env


@dataclass(frozen=True)
class Options:
    """Command-line options."""

    seed: int = 0
    """episode seed (scenario draw)"""
    ego_accel: float = 2.0
    """ego acceleration during the first 4 s [m/s^2]"""
    steps: int = 100
    """episode length [steps of 0.1 s]"""


def parse_options() -> Options:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for name, default in Options.__dataclass_fields__.items():
        parser.add_argument(
            f"--{name.replace('_', '-')}", type=type(default.default), default=default.default
        )
    return Options(**vars(parser.parse_args()))


def main(options: Options) -> dict:
    config = riskflow_env.EnvConfig(
        episode_steps=options.steps, terminate_on_collision="none", terminate_on_offroad="none"
    )
    env = riskflow_env.parallel_env(config=config)
    observations, _ = env.reset(seed=options.seed)
    print(f"scene {env.scenario.name!r}: {len(env.agents)} vehicles, seed {options.seed}")
    collisions: set[tuple[str, str]] = set()
    offroad: set[str] = set()
    total_reward = 0.0
    while env.agents:
        step = env.scene.step
        actions = {agent: np.zeros(2) for agent in env.agents}
        if "ego" in actions and step < 40:
            actions["ego"] = np.array([options.ego_accel, 0.0])
        _, rewards, _, _, infos = env.step(actions)
        total_reward += rewards.get("ego", 0.0)
        for agent, info in infos.items():
            for other in info["collided_with"]:
                pair = tuple(sorted((agent, other)))
                if pair not in collisions:
                    collisions.add(pair)
                    print(f"  t={env.scene.step * 0.1:4.1f} s  collision {pair[0]} <-> {pair[1]}")
            if info["offroad_fraction"] > 0 and agent not in offroad:
                offroad.add(agent)
                print(
                    f"  t={env.scene.step * 0.1:4.1f} s  off-road  {agent} "
                    f"({info['offroad_fraction']:.0%} of footprint, {info['sdf_depth']:.2f} m)"
                )
    summary = {
        "collisions": len(collisions),
        "offroad_agents": len(offroad),
        "ego_return": round(total_reward, 3),
    }
    print("summary:", summary)
    env.close()
    return summary


if __name__ == "__main__":
    main(parse_options())
