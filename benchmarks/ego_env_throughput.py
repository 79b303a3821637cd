"""Ego env-steps per second against the K = 5 RiskFlow adversary: the vector env vs a loop.

N scenes of the ego's training env, the other vehicles driven by the ``--method``
adversary (default ``riskflow``, built by :func:`policies.registry.build_policy` with the
library's defaults: the shipped checkpoint on the realistic base; ``riskflow-raw`` is the
raw generator), the ego holding speed and heading (action 0), finished episodes reset
(scenes drawn from the shipped ``--split`` bank), in two ways measured in one run:

* **vector**: :class:`policies.rl.vector_env.EgoVectorEnv`, the N scenes stepped by one
  batched transition and planned by one ``BatchedAdversary`` call per cycle;
* **loop**: N ``EgoTrainingEnv`` (``EgoEnv``) stepped one after the other in one process
  (as SB3's ``DummyVecEnv`` does), each adversary planning its own scene.

Both see the same scenes (seeds ``b``), the same model and the same actions. Reported per
N: ego env-steps per second (N x steps / seconds) of each and their ratio. Each round
times ``--steps`` steps of all N scenes after one warm-up step; rounds alternate (vector,
then loop) and the best of ``--rounds`` is kept.

    python benchmarks/ego_env_throughput.py [--scenes 1 8 32] [--steps 20] [--device cpu]
    python benchmarks/ego_env_throughput.py --device cuda --loop-device cpu  # GPU vs CPU
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
from methods import make_policy
from tqdm import tqdm

from policies.cli_inputs import check_device
from policies.dataclass_cli import check_at_least, check_choices, check_sizes, parse_dataclass
from policies.registry import method_spec
from policies.rl.envs import EgoTrainingEnv
from policies.rl.vector_env import EgoVectorEnv
from riskflow_env.cli_errors import run_script
from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import SPLITS, shipped_bank
from riskflow_env.view import ScenePolicy
from riskflow_env.wrappers import EgoEnv


@dataclass(frozen=True)
class Options:
    """Benchmark options."""

    scenes: tuple[int, ...] = (1, 8, 32)
    """scenes stepped together (N)"""
    steps: int = 20
    """timed steps of all N scenes per round"""
    rounds: int = 1
    """timed rounds per N and way; the best is reported"""
    method: str = "riskflow"
    """the adversary (riskflow-eval --list; e.g. riskflow-raw, strive)"""
    k: int = 5
    """size of the controllable set A_c in each scene"""
    guidance_steps: int | None = None
    """K_g guidance steps per planning cycle; default: the method's"""
    episode_steps: int = 100
    """episode length [steps of 0.1 s]"""
    split: str = "eval"
    """shipped scenario bank the scenes are drawn from"""
    threads: int = 1
    """torch CPU threads"""
    device: str = "cpu"
    """torch device (cuda where a GPU is present)"""
    loop_device: str | None = None
    """torch device of the loop's adversaries (None: --device); ``--device cuda
    --loop-device cpu`` compares the vector env on the GPU with the loop on the CPU"""

    def __post_init__(self) -> None:
        lows = {"steps": 1, "rounds": 1, "k": 0, "guidance_steps": 0, "episode_steps": 1}
        check_at_least(self, lows | {"threads": 1}, ("guidance_steps",), highs={"threads": 256})
        check_sizes(self, ("scenes",))
        check_choices(self, {"split": SPLITS})
        check_device(self.device)
        if self.loop_device is not None:
            check_device(self.loop_device, "--loop-device")
        if not method_spec(self.method).uses_k:
            raise ValueError(f"--method: {self.method!r} is not an adversary (it has no K)")


def _parse(argv: list[str] | None = None) -> Options:
    return parse_dataclass(
        Options, argv, prog="ego_env_throughput.py", description=__doc__.split("\n")[0], debug=True
    )


def _time(step, steps: int) -> float:
    start = time.perf_counter()
    for _ in range(steps):
        step()
    return time.perf_counter() - start


def measure(
    policy: ScenePolicy,
    loop_policy: ScenePolicy,
    count: int,
    config: EnvConfig,
    options: Options,
) -> dict:
    """Best seconds for ``options.steps`` steps of ``count`` scenes, vector (``policy``) and
    loop (copies of ``loop_policy``)."""
    scenes = list(shipped_bank(options.split))
    vector = EgoVectorEnv(count, config=config, scenarios=scenes, policy=policy)
    vector.reset(seed=0)
    loop = [
        EgoTrainingEnv(EgoEnv(config=config, scenarios=scenes, policy=loop_policy.spawn(index)))
        for index in range(count)
    ]
    for index, env in enumerate(loop):
        env.reset(seed=index)
    actions = np.zeros((count, 2))

    def step_vector() -> None:
        vector.step(actions)

    def step_loop() -> None:
        for env in loop:
            _, _, terminated, truncated, _ = env.step(actions[0])
            if terminated or truncated:
                env.reset()

    step_vector()  # warm-up: the first planning cycle, the map stack
    step_loop()
    best = {"vector": float("inf"), "loop": float("inf")}
    for _ in range(options.rounds):
        best["vector"] = min(best["vector"], _time(step_vector, options.steps))
        best["loop"] = min(best["loop"], _time(step_loop, options.steps))
    agents = [int(view.present.sum()) for view in vector.scenes.views()]
    return {"scenes": count, "agents": agents, **best}


def main(argv: list[str] | None = None) -> list[dict]:
    """Print the table; returns its rows (``scenes``, ``vector`` and ``loop`` [s for
    ``steps`` steps of all scenes], ``agents`` per scene at the end)."""
    options = _parse(argv)
    torch.set_num_threads(options.threads)

    steps = {} if options.guidance_steps is None else {"guidance_steps": options.guidance_steps}

    def adversary(device: str) -> ScenePolicy:
        extra = {"threads": options.threads, **steps}
        return make_policy(options.method, extra, k=options.k, device=device)

    policy = adversary(options.device)
    loop_device = options.loop_device or options.device
    loop_policy = policy if loop_device == options.device else adversary(loop_device)
    config = EnvConfig(episode_steps=options.episode_steps)
    print(
        f"ego env-steps/s, {options.method} adversary K = {options.k}, K_g = "
        f"{options.guidance_steps or 'the default'}, shipped checkpoint, device "
        f"{options.device} (loop: {loop_device}), {options.threads} torch thread(s); shipped "
        f"{options.split} scenes, "
        f"{options.episode_steps}-step episodes; best of {options.rounds} round(s) of "
        f"{options.steps} steps\n"
    )
    print(f"{'N':>4}{'vector steps/s':>16}{'loop steps/s':>14}{'ratio':>8}{'vehicles':>12}")
    rows = []
    for count in tqdm(options.scenes, "scene counts", leave=False):  # stderr
        row = measure(policy, loop_policy, count, config, options)
        rows.append(row)
        vector = count * options.steps / row["vector"]
        loop = count * options.steps / row["loop"]
        agents = row["agents"]
        print(
            f"{count:>4}{vector:>16.1f}{loop:>14.1f}{vector / loop:>7.2f}x"
            f"{f'{min(agents)}-{max(agents)}':>12}"
        )
    print("\nsteps/s = ego env-steps per second (N scenes x steps / s); ratio = vector / loop")
    return rows


if __name__ == "__main__":
    run_script("ego_env_throughput.py", main)
