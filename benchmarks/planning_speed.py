"""Latency of one RiskFlow planning cycle, phase by phase, against peers in the same run.

One cycle of :class:`policies.riskflow.policy.RiskFlowAdversary` on the raw base with the
paper's objective and step (``avoid_steps=0, hold_distance=0, stitch_first=False,
lambda_sep=0, step_size=0.1``: ``riskflow-eval``'s ``riskflow-plain`` plans the same way)
on a shipped evaluation scene with ``--agents`` vehicles (20) and a 52-step plan: window
building (``window_from_view``), scene encoder, MeanFlow one-step generator, TTC causal
ranking and ``--guidance-steps`` (30) steps of output-space guidance on the top-``--k``
agents.
Peers, measured interleaved with it (same machine load):

* **unguided** — the same policy with ``k = 0`` (window + encoder + generator + ranking);
* **re-sampling** — the gradient-free alternative to guidance: one batched pass drawing
  ``--guidance-steps`` plans per agent (``sample(num_samples=N)``), then keeping the
  sample whose ``A_c`` rows score the lowest ``L_adv``;
* **on the realistic base** — RiskFlow and the unguided generator with ``--avoid-steps``
  avoidance steps (the default's, ``DEFAULT_AVOID_STEPS``: 20), the default holding at
  rest (4 m), blending first and (RiskFlow) the separation term ``lambda_sep = 100`` and
  the step 0.01: the library's defaults (``riskflow-eval``'s ``riskflow`` and ``bits``;
  docs/REALISM.md, rounds 8-18 and 26);
  ``--avoid-steps 0`` leaves these rows out.

Prints the median [ms] of each phase and the ratios to the peers. Target: a full cycle
within 50 ms on a laptop-class CPU. Speed does not depend on the weights: without the
shipped checkpoint the default-size model is randomly initialised.

    python benchmarks/planning_speed.py [--agents 20] [--threads 1] [--repeats 30]
        [--avoid-steps 20]
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass

import numpy as np
import torch
from timing import interleaved_ms

import riskflow_env
from policies.dataclass_cli import parse_dataclass
from policies.learned.config import ModelConfig
from policies.learned.data import ActionNormalizer
from policies.learned.generator import RiskFlowGenerator
from policies.learned.guidance_losses import adversarial_loss
from policies.learned.plan_avoidance import DEFAULT_AVOID_STEPS
from policies.learned.ranking import rank_window
from policies.learned.sampler import sample
from policies.learned.window_types import collate_windows
from policies.learned.windows import window_from_view
from policies.riskflow.policy import PHASES, RiskFlowAdversary
from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import shipped_bank

FALLBACK_NORMALIZER = ActionNormalizer(mean=(-0.11, -0.02), std=(1.09, 0.12))  # shipped-data scale


@dataclass(frozen=True)
class Options:
    """Benchmark options."""

    agents: int = 20
    """vehicles in the scene (the ego included)"""
    k: int = 5
    """size of the controllable set A_c"""
    guidance_steps: int = 30
    """K_g (also the re-sampling peer's sample count)"""
    threads: int = 1
    """torch CPU threads while planning (0: torch's default)"""
    device: str = "cpu"
    """torch device"""
    repeats: int = 30
    """timed cycles per method (the median is reported)"""
    warmup: int = 3
    """untimed cycles per method first"""
    avoid_steps: int = DEFAULT_AVOID_STEPS
    """avoidance steps of the realistic-base peers (0: no such peers)"""

    def __post_init__(self) -> None:
        if self.avoid_steps < 0:
            raise ValueError(f"--avoid-steps must be >= 0, got {self.avoid_steps}")


def _parse(argv: list[str] | None = None) -> Options:
    return parse_dataclass(
        Options, argv, prog="planning_speed.py", description=__doc__.split("\n")[0]
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


def main(argv: list[str] | None = None) -> None:
    options = _parse(argv)
    threads = options.threads or None
    model, normalizer, origin = load_model(options.device)
    view, scene_name = scene_view(options.agents)
    common = dict(generator=model, normalizer=normalizer, device=options.device, threads=threads)
    # the raw base and the paper's objective (riskflow-plain)
    kwargs = dict(
        common,
        avoid_steps=0,
        hold_distance=0.0,
        stitch_first=False,
        lambda_sep=0.0,
        step_size=0.1,
    )
    guided = RiskFlowAdversary(k=options.k, guidance_steps=options.guidance_steps, **kwargs)
    unguided = RiskFlowAdversary(k=0, **kwargs)
    kwargs_based = dict(common, avoid_steps=options.avoid_steps)  # the defaults otherwise
    based = [
        RiskFlowAdversary(k=options.k, guidance_steps=options.guidance_steps, **kwargs_based),
        RiskFlowAdversary(k=0, **kwargs_based),
    ]
    for policy in (guided, unguided, *based):
        policy.reset(view)

    phases: dict[str, list[float]] = {phase: [] for phase in (*PHASES, "total")}

    def guided_cycle() -> None:
        guided.plan(view)
        for phase in phases:
            phases[phase].append(1e3 * guided.timings[phase])

    def resample() -> None:
        previous = torch.get_num_threads()
        torch.set_num_threads(threads or previous)
        try:
            resampling_cycle(guided, view, options.guidance_steps)
        finally:
            torch.set_num_threads(previous)

    cycles = {"riskflow": guided_cycle, "unguided": lambda: unguided.plan(view)}
    cycles["resample"] = resample
    if options.avoid_steps:
        cycles["riskflow-avoid"] = lambda: based[0].plan(view)
        cycles["unguided-avoid"] = lambda: based[1].plan(view)
    walls = interleaved_ms(cycles, options.repeats, options.warmup)
    med = {name: statistics.median(values) for name, values in walls.items()}
    print(
        f"RiskFlow planning cycle: {scene_name}, {int(guided.plan_mask.sum())} agents, "
        f"{model.config.future_steps}-step plans, K = {options.k}, K_g = {options.guidance_steps}"
        f"\nmodel: {model.num_parameters():,} parameters, {origin}; device {options.device}, "
        f"{threads or torch.get_num_threads()} CPU thread(s); median of {options.repeats} cycles\n"
    )
    total = statistics.median(phases["total"])
    print(f"{'phase':<34}{'ms':>9}{'share':>8}")
    for phase in PHASES:
        value = statistics.median(phases[phase])
        print(f"{phase:<34}{value:9.2f}{value / total:8.0%}")
    per_step = statistics.median(phases["guidance"]) / max(options.guidance_steps, 1)
    print(f"{'  guidance, per step':<34}{per_step:9.2f}")
    print(f"{'total (policy timer)':<34}{total:9.2f}")
    print(f"{'total (wall, incl. bookkeeping)':<34}{med['riskflow']:9.2f}\n")
    print(f"{'method':<34}{'ms':>9}{'RiskFlow / it':>15}")
    rows = [
        (f"RiskFlow, K={options.k}, {options.guidance_steps} guidance steps", med["riskflow"]),
        ("unguided generator (K=0)", med["unguided"]),
        (f"re-sampling, best of {options.guidance_steps} samples", med["resample"]),
    ]
    if options.avoid_steps:
        rows += [
            (f"RiskFlow, {options.avoid_steps} avoidance steps", med["riskflow-avoid"]),
            (f"unguided, {options.avoid_steps} avoidance steps", med["unguided-avoid"]),
        ]
    for name, value in rows:
        print(f"{name:<34}{value:9.2f}{med['riskflow'] / value:14.2f}x")
    verdict = "meets" if med["riskflow"] <= 50.0 else "misses"
    print(f"\ntarget <= 50 ms per cycle: {verdict} ({med['riskflow']:.1f} ms)")
    spread = np.percentile(walls["riskflow"], [10, 90])
    print(f"RiskFlow cycle p10-p90: {spread[0]:.1f}-{spread[1]:.1f} ms")


if __name__ == "__main__":
    main()
