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

Each riskflow figure is measured on both step paths in the same run (``--paths``): the
compiled one (:mod:`riskflow_env.compiled`, numba; numpy float64 only, the other
backends and dtypes run the reference on both) and the array-API reference
(``RISKFLOW_COMPILED=0``). The compiled path's one-off start-up (numba import, kernel
compilation into a fresh cache, and loading them from it) is measured in subprocesses and
printed first (``--no-startup`` skips it).

Rates are the best of ``--rounds`` interleaved rounds of ``--seconds`` each (the machine
may be shared; the best round is the least disturbed one).

    python benchmarks/step_throughput.py [--seconds 2] [--rounds 3] [--vehicles 8 16 32 64]
    python benchmarks/step_throughput.py --no-api --batch-scenes 128 1024 --dtype float32
    python benchmarks/step_throughput.py --no-api --backend torch --device cuda
"""

from __future__ import annotations

import cProfile
import pstats
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import gymnasium
import highway_env  # noqa: F401 - registers highway-v0
import numpy as np
from timing import startup_runs, step_path
from tqdm import tqdm

import riskflow_env
from policies.cli_inputs import check_device
from policies.dataclass_cli import check_sizes, parse_dataclass
from riskflow_env import batched, compiled
from riskflow_env.cli_errors import run_script
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
    paths: tuple[str, ...] = ("compiled", "reference")
    """step paths measured: 'compiled' (riskflow_env.compiled, numba) and 'reference'"""
    startup: bool = True
    """measure the compiled path's one-off start-up in subprocesses (cold and cached)"""
    profile: bool = True
    """after table 1, what limits its largest row on each path: cProfile's top entries"""


def _parse(argv: list[str] | None = None) -> Options:
    options = parse_dataclass(
        Options, argv, prog="step_throughput.py", description=__doc__.split("\n")[0], debug=True
    )
    error = usage_error(options)
    if error:
        raise SystemExit(f"step_throughput.py: error: {error}")
    return options


def usage_error(options: Options) -> str | None:
    """What is wrong with the options, in one line (None: nothing)."""
    try:
        check_sizes(options, ("vehicles", "batch_agents", "batch_scenes"), 1, 1024)
    except ValueError as err:
        return str(err)
    if not (options.seconds > 0 and options.seconds < 3600) or options.rounds < 1:
        return f"--seconds in (0, 3600) and --rounds >= 1, got {options.seconds}, {options.rounds}"
    if options.backend not in ("numpy", "torch"):
        return f"--backend must be 'numpy' or 'torch', got {options.backend!r}"
    if options.dtype not in ("float64", "float32"):
        return f"--dtype must be 'float64' or 'float32', got {options.dtype!r}"
    if options.backend == "numpy" and options.device != "cpu":
        return f"--device {options.device} needs --backend torch"
    if not options.paths or set(options.paths) - {"compiled", "reference"}:
        return f"--paths must name 'compiled' and/or 'reference', got {options.paths}"
    try:
        check_device(options.device)
    except ValueError as err:
        return str(err)
    return None


_STARTUP = """
import time
from riskflow_env import batched, compiled
from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import shipped_bank
scenario = shipped_bank("eval")[0]
state = batched.reset_batch([scenario], 8)
start = time.perf_counter()
assert compiled.enabled()
imported = loaded = time.perf_counter()
batched.step_batch(state, state.last_action, scenario.map, EnvConfig(max_agents=8))
print(imported - start, time.perf_counter() - loaded)
"""


def startup_seconds() -> dict[str, float]:
    """The compiled path's one-off costs [s], each in a fresh process: importing numba and
    the kernels, the first step with an empty kernel cache (compilation) and with the
    cache that run filled (loading)."""
    return startup_runs(_STARTUP)


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
        count, steps, start = 0, 0, time.perf_counter()
        while not steps or time.perf_counter() - start < seconds:  # one step at least
            count += int(state.active.sum())
            steps += 1
            state, _ = batched.step_batch(state, actions, drivable_map, config, observations)
        return count, time.perf_counter() - start

    return run


def limits(run: Callable[[float], tuple[int, float]], seconds: float, top: int = 6) -> list[str]:
    """The ``top`` functions of a cProfile of ``run`` by own time, each with its share."""
    profile = cProfile.Profile()
    profile.enable()
    run(seconds)
    profile.disable()
    stats = pstats.Stats(profile).stats  # (file, line, name) -> (calls, _, own, cumulative, _)
    total = sum(entry[2] for entry in stats.values()) or 1.0
    ranked = sorted(stats.items(), key=lambda item: item[1][2], reverse=True)[:top]
    return [
        f"  {100 * own / total:5.1f}%  {name} ({Path(file).name}:{line}), {calls:,} calls"
        for (file, line, name), (calls, _, own, _, _) in ranked
    ]


def main(argv: list[str] | None = None) -> dict[str, list[dict]]:
    """Print the tables; returns their rows: ``api`` (vehicles, path, highway, riskflow
    [vehicle-steps/s]), ``batched`` (agents, scenes, observations, path, rate
    [agent-steps/s]) and ``startup`` ([s], empty with --no-startup)."""
    options = _parse(argv)
    paths = options.paths
    if compiled.kernels() is None and "compiled" in paths:
        print("numba is not installed: the 'compiled' rows run the reference")
    api_rows = len(options.vehicles) if options.api else 0
    rows = api_rows + 2 * len(options.batch_agents) * len(options.batch_scenes)
    bar = tqdm(total=rows, desc="benchmark rows", unit="row", leave=False)  # on stderr
    write = bar.write  # a table line on stdout, above the bar
    results: dict[str, list[dict]] = {"api": [], "batched": [], "startup": []}
    if options.startup and "compiled" in paths and compiled.kernels() is not None:
        seconds = startup_seconds()
        results["startup"].append(seconds)
        write(
            "Compiled path start-up, once per process (fresh processes): numba import "
            f"{seconds['import']:.2f} s; first step {seconds['compile']:.2f} s with an empty "
            f"kernel cache (compilation, once per machine), {seconds['load']:.2f} s cached\n"
        )
    if "compiled" in paths:  # load (or compile) the kernels before anything is timed
        with step_path("compiled"):
            rate(batched_run(4, 2, True), 0.0)
    if options.api:
        write("PettingZoo API (full observations for every agent) vs highway-env, dt = 0.1 s")
        write(
            "| vehicles | step path | highway-env vehicle-steps/s | riskflow env steps/s "
            "| riskflow agent-steps/s | ratio |"
        )
        write("| ---: | :--- | ---: | ---: | ---: | ---: |")
    for vehicles in options.vehicles if options.api else ():
        runs = {"highway": highway_env_run(vehicles)}
        runs.update({path: riskflow_run(vehicles) for path in paths})
        best = dict.fromkeys(runs, 0.0)
        for _ in range(options.rounds):
            for name, run in runs.items():
                with step_path(name):
                    best[name] = max(best[name], rate(run, options.seconds))
        for path in paths:
            env_steps = best[path] * runs[path].steps_per_agent_step
            write(
                f"| {vehicles} | {path} | {best['highway']:,.0f} | {env_steps:,.0f} "
                f"| {best[path]:,.0f} | {best[path] / best['highway']:.1f}x |"
            )
            results["api"].append(
                {
                    "vehicles": vehicles,
                    "path": path,
                    "highway": best["highway"],
                    "riskflow": best[path],
                }
            )
        bar.update()

    if options.api and options.profile and options.vehicles:
        vehicles = max(options.vehicles)
        for path in paths:
            with step_path(path):
                write(
                    f"\nWhat limits {vehicles} vehicles on the {path} path (cProfile of "
                    "the steps and the resets between episodes):"
                )
                for line in limits(riskflow_run(vehicles), options.seconds):
                    write(line)

    where = options.backend + (f" on {options.device}" if options.backend == "torch" else "")
    write(f"\nBatched stepping (riskflow_env.batched, {where} {options.dtype}, one map per batch)")
    if options.backend != "numpy" or options.dtype != "float64":
        write("(the compiled path takes numpy float64 only: every path runs the reference here)")
    columns = " | ".join(f"{path} agent-steps/s" for path in paths)
    write(f"| agents A | scenes B | observations | {columns} |")
    write("| ---: | ---: | :---: |" + " ---: |" * len(paths))
    for agents in options.batch_agents:
        for scenes in options.batch_scenes:
            for observations in (True, False):
                run = batched_run(agents, scenes, observations, converter(options))
                best = dict.fromkeys(paths, 0.0)
                for _ in range(options.rounds):
                    for path in paths:
                        with step_path(path):
                            best[path] = max(best[path], rate(run, options.seconds))
                cells = " | ".join(f"{best[path]:,.0f}" for path in paths)
                write(f"| {agents} | {scenes} | {'yes' if observations else 'no'} | {cells} |")
                for path in paths:
                    results["batched"].append(
                        {
                            "agents": agents,
                            "scenes": scenes,
                            "observations": observations,
                            "path": path,
                            "rate": best[path],
                        }
                    )
                bar.update()
    bar.close()
    return results


if __name__ == "__main__":
    run_script("step_throughput.py", main)
