"""Stepping speed of ``riskflow_v0`` against highway-env, measured in one run.

Two tables:

1. **PettingZoo API vs highway-env**, same road family (highway-env ``highway-v0``, 4
   lanes), same number of vehicles N (8, 16, 32, 64, the ego included), same time step
   (0.1 s: highway-env with ``simulation_frequency=10, policy_frequency=10``), 10 s
   episodes; only ``step`` calls are timed, not resets. highway-env's vehicles are
   driven by its own IDM/MOBIL models (ego: ``IDLE``) and it observes the ego only;
   riskflow steps every vehicle with an action given from outside (zeros here) and
   returns full observations, rewards and infos for every agent. Counted: vehicle-steps
   (live vehicles x steps) per second.
2. **Batched stepping** (:mod:`riskflow_env.batched`): B scenes x A agents per call
   (scenes share one highway map), with and without observations; agent-steps per second.

Rates are the best of ``--rounds`` interleaved rounds of ``--seconds`` each (the machine
may be shared; the best round is the least disturbed one).

    python benchmarks/step_throughput.py [--seconds 2] [--rounds 3] [--vehicles 8 16 32 64]
    python benchmarks/step_throughput.py --no-api --batch-scenes 128 1024 --dtype float32
    python benchmarks/step_throughput.py --no-api --backend torch --device cuda
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import gymnasium
import highway_env  # noqa: F401 - registers highway-v0
import numpy as np
from tqdm import tqdm

import riskflow_env
from policies.dataclass_cli import parse_dataclass
from riskflow_env import batched
from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import HighwayTrafficSource, TrafficConfig, place_traffic

HIGHWAY_IDLE = 1  # highway-env DiscreteMetaAction index of IDLE
EPISODE_SECONDS = 10  # [s] episode length of both simulators


@dataclass(frozen=True)
class Options:
    """Benchmark options."""

    seconds: float = 2.0
    """timed seconds per simulator, per round and row"""
    rounds: int = 3
    """interleaved rounds; the best rate of each simulator is reported"""
    vehicles: tuple[int, ...] = (8, 16, 32, 64)
    """vehicles per scene, ego included"""
    api: bool = True
    """run table 1 (PettingZoo API vs highway-env); --no-api: the batched rows only"""
    batch_agents: tuple[int, ...] = (8, 32)
    """agent slots per scene of the batched rows"""
    batch_scenes: tuple[int, ...] = (1, 16, 128)
    """scenes per batch"""
    backend: str = "numpy"
    """arrays of the batched rows: 'numpy' or 'torch' (SceneState.convert)"""
    device: str = "cpu"
    """torch device of the batched rows with --backend torch ('cpu', 'cuda')"""
    dtype: str = "float64"
    """float dtype of the batched rows: 'float64' (the env's) or 'float32' (about 1.5-2x
    the agent-steps/s on a CPU; states differ from float64 by ~1e-4 m after 50 steps)"""


def _parse(argv: list[str] | None = None) -> Options:
    options = parse_dataclass(
        Options, argv, prog="step_throughput.py", description=__doc__.split("\n")[0]
    )
    if options.backend not in ("numpy", "torch"):
        raise SystemExit(f"--backend must be 'numpy' or 'torch', got {options.backend!r}")
    if options.dtype not in ("float64", "float32"):
        raise SystemExit(f"--dtype must be 'float64' or 'float32', got {options.dtype!r}")
    if options.backend == "numpy" and options.device != "cpu":
        raise SystemExit(f"--device {options.device} needs --backend torch")
    return options


def converter(options: Options) -> Callable:
    """The array conversion of the batched rows (``SceneState.convert``): float arrays to
    ``--dtype``, and to torch tensors on ``--device`` with ``--backend torch``."""
    float_type = np.dtype(options.dtype)

    def convert(array):
        array = np.asarray(array)
        if array.dtype.kind == "f":
            array = array.astype(float_type)
        if options.backend == "torch":
            import torch

            return torch.as_tensor(array, device=options.device)
        return array

    return convert


def traffic(vehicles: int) -> TrafficConfig:
    """Highway traffic with exactly ``vehicles`` cars (a 0.6 s headway fits 64 on 600 m)."""
    return TrafficConfig(
        families=("highway",), num_vehicles=(vehicles, vehicles), radius=600.0, time_headway=0.6
    )


def rate(run: Callable[[float], tuple[int, float]], seconds: float) -> float:
    """Units per second of ``run(seconds) -> (units, elapsed)``."""
    units, elapsed = run(seconds)
    return units / elapsed


def highway_env_run(vehicles: int) -> Callable[[float], tuple[int, float]]:
    """highway-env stepping for ``seconds``: (vehicle-steps, elapsed)."""
    env = gymnasium.make(
        "highway-v0",
        config={
            "vehicles_count": vehicles - 1,  # others; the ego is added
            "simulation_frequency": 10,
            "policy_frequency": 10,
            "duration": EPISODE_SECONDS,
        },
    )
    env.reset(seed=0)
    road = env.unwrapped.road

    def run(seconds: float) -> tuple[int, float]:
        nonlocal road
        count, elapsed = 0, 0.0
        while elapsed < seconds:
            count += len(road.vehicles)
            start = time.perf_counter()
            _, _, terminated, truncated, _ = env.step(HIGHWAY_IDLE)
            elapsed += time.perf_counter() - start
            if terminated or truncated:  # resets are not timed
                env.reset()
                road = env.unwrapped.road
        return count, elapsed

    return run


def riskflow_run(vehicles: int) -> Callable[[float], tuple[int, float]]:
    """riskflow_v0 stepping through the PettingZoo API: (agent-steps, elapsed); the env
    steps of the last run are kept in ``run.env_steps``."""
    env = riskflow_env.parallel_env(
        config=EnvConfig(max_agents=vehicles, episode_steps=EPISODE_SECONDS * 10),
        scenarios=HighwayTrafficSource(traffic(vehicles)),
    )
    env.reset(seed=0)
    zero = np.zeros(2)

    def run(seconds: float) -> tuple[int, float]:
        count, steps, elapsed = 0, 0, 0.0
        while elapsed < seconds:
            count += len(env.agents)
            steps += 1
            start = time.perf_counter()
            env.step({agent: zero for agent in env.agents})
            elapsed += time.perf_counter() - start
            if not env.agents:  # resets are not timed
                env.reset()
        run.steps_per_agent_step = steps / max(count, 1)
        return count, elapsed

    return run


def batched_run(
    agents: int, scenes: int, observations: bool, convert: Callable = np.asarray
) -> Callable:
    """Batched stepping of ``scenes`` highway scenes, arrays through ``convert``:
    (agent-steps, elapsed)."""
    rng = np.random.default_rng(0)
    drivable_map = HighwayTrafficSource(traffic(agents)).sample(rng, agents).map
    pool = [place_traffic(drivable_map, agents, rng, traffic(agents)) for _ in range(8)]
    scenarios = [pool[k % len(pool)] for k in range(scenes)]
    config = EnvConfig(
        max_agents=agents,
        episode_steps=10_000_000,  # the largest EnvConfig takes: no episode ends
        terminate_on_collision="none",
        terminate_on_offroad="none",
    )
    state = batched.reset_batch(scenarios, agents).convert(convert)
    actions = convert(np.zeros((scenes, agents, 2)))

    def run(seconds: float) -> tuple[int, float]:
        nonlocal state
        count, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            count += int(state.active.sum())
            state, _ = batched.step_batch(state, actions, drivable_map, config, observations)
        return count, time.perf_counter() - start

    return run


def main(argv: list[str] | None = None) -> dict[str, list[dict]]:
    """Print the tables; returns their rows: ``api`` (vehicles, highway, riskflow
    [vehicle-steps/s]) and ``batched`` (agents, scenes, observations, rate [agent-steps/s])."""
    options = _parse(argv)
    api_rows = len(options.vehicles) if options.api else 0
    rows = api_rows + 2 * len(options.batch_agents) * len(options.batch_scenes)
    bar = tqdm(total=rows, desc="benchmark rows", unit="row", leave=False)  # on stderr
    write = bar.write  # a table line on stdout, above the bar
    results: dict[str, list[dict]] = {"api": [], "batched": []}
    if options.api:
        write("PettingZoo API (full observations for every agent) vs highway-env, dt = 0.1 s")
        write(
            "| vehicles | highway-env vehicle-steps/s | riskflow env steps/s "
            "| riskflow agent-steps/s | ratio |"
        )
        write("| ---: | ---: | ---: | ---: | ---: |")
    for vehicles in options.vehicles if options.api else ():
        runs = {"highway": highway_env_run(vehicles), "riskflow": riskflow_run(vehicles)}
        best = dict.fromkeys(runs, 0.0)
        for _ in range(options.rounds):
            for name, run in runs.items():
                best[name] = max(best[name], rate(run, options.seconds))
        env_steps = best["riskflow"] * runs["riskflow"].steps_per_agent_step
        write(
            f"| {vehicles} | {best['highway']:,.0f} | {env_steps:,.0f} "
            f"| {best['riskflow']:,.0f} | {best['riskflow'] / best['highway']:.1f}x |"
        )
        results["api"].append({"vehicles": vehicles, **best})
        bar.update()

    where = options.backend + (f" on {options.device}" if options.backend == "torch" else "")
    write(f"\nBatched stepping (riskflow_env.batched, {where} {options.dtype}, one map per batch)")
    write("| agents A | scenes B | observations | agent-steps/s |")
    write("| ---: | ---: | :---: | ---: |")
    for agents in options.batch_agents:
        for scenes in options.batch_scenes:
            for observations in (True, False):
                run = batched_run(agents, scenes, observations, converter(options))
                best = max(rate(run, options.seconds) for _ in range(options.rounds))
                write(f"| {agents} | {scenes} | {'yes' if observations else 'no'} | {best:,.0f} |")
                results["batched"].append(
                    {"agents": agents, "scenes": scenes, "observations": observations, "rate": best}
                )
                bar.update()
    bar.close()
    return results


if __name__ == "__main__":
    main()
