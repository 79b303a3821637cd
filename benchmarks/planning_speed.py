"""Latency of one RiskFlow planning cycle, phase by phase, against peers in the same run.

One cycle of ``riskflow`` (:func:`policies.registry.build_policy` with no options: the
library's default, on the realistic base) on a shipped evaluation scene with
``--agents`` vehicles (20) and a 52-step plan: window building (``window_from_view``),
scene encoder, MeanFlow one-step generator, avoidance steps, TTC causal ranking and the
default ``K_g`` (30) steps of output-space guidance on the top-``--k`` agents.
Peers, measured interleaved with it (same machine load):

* **unguided** -- ``bits``, the unguided generator on the same realistic base;
* **re-sampling** -- the gradient-free alternative to guidance: one batched pass drawing
  ``K_g`` plans per agent (``sample(num_samples=N)``), then keeping the sample whose
  ``A_c`` rows score the lowest ``L_adv``;
* **raw** (``--raw``) -- ``riskflow-raw`` and ``bits-raw``, the same methods on the raw
  generator (no avoidance steps, no holding at rest), with the ratio of each default
  cycle to its raw one;
* **reference loops** -- the default cycle with the compiled avoidance and guidance loops
  off (``RISKFLOW_COMPILED=0``, :mod:`policies.learned.compiled_plans`): the torch
  reference; ``--no-reference`` skips it. Where numba is not installed both rows run the
  reference.

The compiled loops' one-off start-up (importing numba and the kernels, compiling them on a
machine's first run, loading them from numba's cache after) is measured in fresh
processes and printed last (``--no-startup`` skips it).

Prints the median [ms] of each phase and the ratios to the peers. Speed does not depend
on the weights: without the shipped checkpoint the default-size model is randomly
initialised.

    python benchmarks/planning_speed.py [--agents 20] [--threads 1] [--repeats 30] [--raw]
"""

from __future__ import annotations

import os
import statistics
from dataclasses import dataclass

import numpy as np
import torch
from methods import make_policy, raw_variant
from timing import interleaved_ms, startup_runs, step_path

import riskflow_env
from policies.cli_inputs import check_device
from policies.dataclass_cli import check_at_least, parse_dataclass
from policies.learned import compiled_plans
from policies.learned.config import ModelConfig
from policies.learned.data import ActionNormalizer
from policies.learned.generator import RiskFlowGenerator
from policies.learned.guidance_losses import adversarial_loss
from policies.learned.ranking import rank_window
from policies.learned.sampler import sample
from policies.learned.window_types import collate_windows
from policies.learned.windows import window_from_view
from policies.registry import method_spec
from policies.riskflow.policy import PHASES, RiskFlowAdversary
from riskflow_env.cli_errors import run_script
from riskflow_env.config import EnvConfig
from riskflow_env.processes import MAX_THREADS
from riskflow_env.scenarios import shipped_bank

FALLBACK_NORMALIZER = ActionNormalizer(mean=(-0.11, -0.02), std=(1.09, 0.12))  # shipped-data scale


@dataclass(frozen=True)
class Options:
    """Benchmark options."""

    agents: int = 20
    """vehicles in the scene (the ego included)"""
    k: int = 5
    """size of the controllable set A_c"""
    guidance_steps: int | None = None
    """K_g (also the re-sampling peer's sample count); default: the policy's"""
    threads: int = 1
    """torch CPU threads while planning (0: torch's default)"""
    device: str = "cpu"
    """torch device"""
    repeats: int = 30
    """timed cycles per method (the median is reported)"""
    warmup: int = 3
    """untimed cycles per method first"""
    raw: bool = False
    """also riskflow-raw and bits-raw, the raw generator without the rule layer"""
    reference: bool = True
    """also the default cycle with the compiled planning loops off (the torch reference)"""
    startup: bool = True
    """measure the compiled loops' one-off start-up in fresh processes (cold and cached)"""

    def __post_init__(self) -> None:
        lows = {"agents": 1, "k": 0, "guidance_steps": 1, "threads": 1, "repeats": 1, "warmup": 0}
        check_at_least(self, lows, ("guidance_steps",), highs={"threads": MAX_THREADS})
        check_device(self.device)


def _parse(argv: list[str] | None = None) -> Options:
    return parse_dataclass(
        Options, argv, prog="planning_speed.py", description=__doc__.split("\n")[0], debug=True
    )


def load_model(device: str) -> tuple[RiskFlowGenerator, ActionNormalizer, str]:
    """The shipped generator, or a random default-size one if it is not there."""
    try:
        from policies.learned.checkpoint import load_generator

        model, normalizer, _ = load_generator(device=device)
        return model, normalizer, "shipped checkpoint"
    except (ImportError, FileNotFoundError):
        torch.manual_seed(0)
        model = RiskFlowGenerator(ModelConfig()).to(device).eval()
        return model, FALLBACK_NORMALIZER, "random weights (no shipped checkpoint)"


def scene_view(agents: int):
    """The view of the first shipped evaluation scene whose window holds ``agents`` vehicles."""
    env = riskflow_env.parallel_env(config=EnvConfig(max_agents=agents))
    for scenario in shipped_bank("eval"):
        if scenario.valid[:, scenario.current_index].sum() < agents:
            continue
        env.reset(seed=0, options={"scenario": scenario})
        if window_from_view(env.view()).agent_mask.sum() == agents:
            return env.view(), scenario.name
    raise SystemExit(f"no shipped evaluation scene has {agents} vehicles within the window")


def resampling_cycle(policy: RiskFlowAdversary, view, samples: int) -> None:
    """Peer: window, encoder, ``samples`` plans in one pass, ranking, pick by ``L_adv``."""
    window = window_from_view(view, policy.window_config)
    batch = collate_windows([window]).to(policy.device)
    generator = torch.Generator(device=policy.device).manual_seed(0)
    with torch.no_grad():
        scene = policy.model.encode(batch)
        _, trajectories = sample(
            policy.model, scene, None, policy.normalizer, num_samples=samples, generator=generator
        )  # (1, N, A, T, 4)
        controllable = torch.from_numpy(rank_window(window, policy.k).controllable)
        others = ~controllable & scene.agent_mask[0].cpu()
        scores = [
            adversarial_loss(plan[controllable, :, :2], plan[others, :, :2])
            for plan in trajectories[0].cpu()
        ]
        int(torch.stack(scores).argmin())


def main(argv: list[str] | None = None) -> dict[str, float]:
    """Print the tables; returns the median cycle [ms] of each method."""
    options = _parse(argv)
    threads = options.threads or None
    model, normalizer, origin = load_model(options.device)
    view, scene_name = scene_view(options.agents)
    models = dict(generator=model, normalizer=normalizer, threads=threads)
    steps = {} if options.guidance_steps is None else {"guidance_steps": options.guidance_steps}
    methods = ("riskflow", "bits")
    if options.raw:
        methods += tuple(raw_variant(name) for name in methods)
    policies = {}
    for name in methods:
        guided_options = steps if method_spec(name).uses_k else {}
        policies[name] = make_policy(
            name, models | guided_options, k=options.k, device=options.device
        )
    for policy in policies.values():
        policy.reset(view)
    guided = policies["riskflow"]
    samples = guided.guidance.steps

    phases: dict[str, list[float]] = {phase: [] for phase in (*PHASES, "total")}

    def guided_cycle() -> None:
        guided.plan(view)
        for phase in phases:
            phases[phase].append(1e3 * guided.timings[phase])

    def resample() -> None:
        previous = torch.get_num_threads()
        torch.set_num_threads(threads or previous)
        try:
            resampling_cycle(guided, view, samples)
        finally:
            torch.set_num_threads(previous)

    def reference_cycle() -> None:
        with step_path("reference"):
            reference.plan(view)

    cycles = {name: (lambda p=policy: p.plan(view)) for name, policy in policies.items()}
    cycles["riskflow"], cycles["resample"] = guided_cycle, resample
    if options.reference:
        reference = make_policy("riskflow", models | steps, k=options.k, device=options.device)
        reference.reset(view)
        cycles["reference"] = reference_cycle
    walls = interleaved_ms(cycles, options.repeats, options.warmup)
    med = {name: statistics.median(values) for name, values in walls.items()}
    print(
        f"riskflow planning cycle (the library's default): {scene_name}, "
        f"{int(guided.plan_mask.sum())} agents, {model.config.future_steps}-step plans, "
        f"K = {options.k}, K_g = {samples}\nmodel: {model.num_parameters():,} parameters, "
        f"{origin}; device {options.device}, {threads or torch.get_num_threads()} CPU "
        f"thread(s); median of {options.repeats} cycles\n"
    )
    total = statistics.median(phases["total"])
    print(f"{'phase':<34}{'ms':>9}{'share':>8}")
    for phase in PHASES:
        value = statistics.median(phases[phase])
        print(f"{phase:<34}{value:9.2f}{value / total:8.0%}")
    per_step = statistics.median(phases["guidance"]) / max(samples, 1)
    print(f"{'  guidance, per step':<34}{per_step:9.2f}")
    print(f"{'total (policy timer)':<34}{total:9.2f}")
    print(f"{'total (wall, incl. bookkeeping)':<34}{med['riskflow']:9.2f}\n")
    labels = {
        "riskflow": f"riskflow, K={options.k}",
        "bits": "bits (unguided, K=0)",
        "resample": f"re-sampling, best of {samples}",
        "riskflow-raw": f"riskflow-raw, K={options.k}",
        "bits-raw": "bits-raw (unguided, K=0)",
        "reference": f"riskflow, K={options.k}, reference loops",
    }
    compiled = compiled_plans.kernels() is not None and options.device == "cpu"
    print(f"planning loops: {'compiled (numba)' if compiled else 'the torch reference'}")
    print(f"{'method':<34}{'ms':>9}{'riskflow / it':>15}")
    for name in (*methods[:2], "resample", *methods[2:], *(("reference",) * options.reference)):
        print(f"{labels[name]:<34}{med[name]:9.2f}{med['riskflow'] / med[name]:14.2f}x")
    if options.raw:
        print("\nrealistic base / raw generator, same method:")
        for name in ("riskflow", "bits"):
            print(f"{name:<34}{med[name] / med[raw_variant(name)]:9.2f}x")
    spread = np.percentile(walls["riskflow"], [10, 90])
    print(f"\nriskflow cycle p10-p90: {spread[0]:.1f}-{spread[1]:.1f} ms")
    if options.startup and compiled:
        costs = startup_seconds(options.agents)
        print(
            "compiled loops' start-up, once per process: import {import:.2f} s, first cycle "
            "{compile:.1f} s with an empty kernel cache (compiling), {load:.2f} s with it "
            "filled (loading), each over a later cycle".format(**costs)
        )
    return med


_STARTUP = """
import sys, time
sys.path.insert(0, {folder!r})
from policies.learned import compiled_plans
start = time.perf_counter()
assert compiled_plans.kernels() is not None
imported = time.perf_counter() - start
from planning_speed import load_model, scene_view
from methods import make_policy
model, normalizer, _ = load_model("cpu")
view, _ = scene_view({agents})
policy = make_policy("riskflow", dict(generator=model, normalizer=normalizer, threads=1))
policy.reset(view)
start = time.perf_counter()
policy.plan(view)
first = time.perf_counter()
policy.plan(view)
print(imported, (first - start) - (time.perf_counter() - first))
"""


def startup_seconds(agents: int) -> dict[str, float]:
    """The compiled loops' one-off costs [s], each in a fresh process: importing numba and
    the kernels, and what the first cycle costs over the next with an empty kernel cache
    (compiling) and with the cache that run filled (loading)."""
    folder = os.path.dirname(os.path.abspath(__file__))
    return startup_runs(_STARTUP.format(folder=folder, agents=agents))


if __name__ == "__main__":
    run_script("planning_speed.py", main)
