"""Speed of the RiskFlow generator: forward latency, and the MeanFlow JVP step vs flow matching.

Prints a table:

* forward latency (scene encoder + one MeanFlow head pass, no grad) of one scene with
  8, 16 and 32 agents: the cost of one planning cycle's one-step sample;
* one training step (forward, loss, backward, Adam) with the MeanFlow JVP objective
  and with plain flow matching (``r = t``, no JVP) on the same batch, their ratio
  (target <= 2.5x) and training throughput in scenes per second.

Batches are synthetic (``policies.learned.synthetic``): speed does not depend on the data.

    python benchmarks/generator_speed.py [--threads 1] [--device cpu] [--repeats 30]
"""

from __future__ import annotations

import statistics
from collections.abc import Callable
from dataclasses import dataclass

import torch
from timing import interleaved_ms

from policies.cli_inputs import check_device
from policies.dataclass_cli import check_at_least, check_sizes, parse_dataclass
from policies.learned.config import ModelConfig
from policies.learned.data import ActionNormalizer
from policies.learned.generator import RiskFlowGenerator
from policies.learned.sampler import base_velocity
from policies.learned.synthetic import synthetic_batch
from policies.riskflow.meanflow import flow_matching_loss, meanflow_loss
from policies.riskflow.time_sampler import TimeSampler
from riskflow_env.cli_errors import run_script
from riskflow_env.processes import MAX_THREADS

NORMALIZER = ActionNormalizer(mean=(0.0, 0.0), std=(1.0, 0.03))  # synthetic-data scale


@dataclass(frozen=True)
class Options:
    """Benchmark options."""

    device: str = "cpu"
    """torch device"""
    threads: int = 0
    """torch CPU threads; 0 keeps torch's default"""
    repeats: int = 30
    """timed repetitions per row (the median is reported)"""
    warmup: int = 5
    """untimed repetitions before each row"""
    agents: tuple[int, ...] = (8, 16, 32)
    """agent counts of the latency rows"""
    train_scenes: int = 16
    """scenes per training batch"""
    train_agents: int = 16
    """agent slots per training scene"""

    def __post_init__(self) -> None:
        check_at_least(self, {"repeats": 1, "warmup": 0, "threads": 0, "train_scenes": 1,
                              "train_agents": 1}, highs={"threads": MAX_THREADS})  # fmt: skip
        check_sizes(self, ("agents",))
        check_device(self.device)


def _parse(argv: list[str] | None = None) -> Options:
    return parse_dataclass(
        Options, argv, prog="generator_speed.py", description=__doc__.split("\n")[0], debug=True
    )


def median_ms(options: Options, *fns: Callable[[], object]) -> list[float]:
    """Median wall time [ms] of each of ``fns`` (CUDA synchronised).

    The functions run in turn within each repetition, so a peer measured in the same
    run sees the same machine load.
    """
    sync = torch.cuda.synchronize if options.device.startswith("cuda") else (lambda: None)
    named = {str(i): fn for i, fn in enumerate(fns)}
    times = interleaved_ms(named, options.repeats, options.warmup, sync)
    return [statistics.median(samples) for samples in times.values()]


def forward_latency(model: RiskFlowGenerator, agents: int, options: Options) -> float:
    """One scene: ``u_theta(eps, 0, 1; C(batch))``, encoder included [ms]."""
    batch = synthetic_batch(1, agents, seed=agents, device=options.device)
    eps = torch.randn(1, agents, model.config.future_steps, 2, device=options.device)

    @torch.no_grad()
    def run() -> torch.Tensor:
        return base_velocity(model, eps, model.encode(batch))

    return median_ms(options, run)[0]


def training_steps(model: RiskFlowGenerator, options: Options) -> tuple[float, float]:
    """Median step times [ms] of the MeanFlow JVP objective and of flow matching."""
    batch = synthetic_batch(
        options.train_scenes, options.train_agents, seed=0, device=options.device
    )
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)
    gen = torch.Generator(device=options.device).manual_seed(0)
    scenes = options.train_scenes

    def step(flow_matching: bool) -> None:
        t, r = TimeSampler(flow_matching=flow_matching)(
            scenes, generator=gen, device=options.device
        )
        eps = torch.randn(batch.actions.shape, generator=gen, device=options.device)
        if flow_matching:
            loss, _ = flow_matching_loss(model, batch, NORMALIZER, eps, t)
        else:
            loss, _ = meanflow_loss(model, batch, NORMALIZER, eps, t, r)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    meanflow_ms, flow_matching_ms = median_ms(options, lambda: step(False), lambda: step(True))
    return meanflow_ms, flow_matching_ms


def main(argv: list[str] | None = None) -> dict[str, float]:
    """Print the table; returns its rows (measurement -> median ms)."""
    options = _parse(argv)
    if options.threads:
        torch.set_num_threads(options.threads)
    torch.manual_seed(0)
    model = RiskFlowGenerator(ModelConfig()).to(options.device)
    print(
        f"RiskFlow generator: {model.num_parameters():,} parameters, device {options.device}, "
        f"{torch.get_num_threads()} CPU thread(s), median of {options.repeats} runs\n"
    )
    rows = [
        (f"forward, 1 scene x {n} agents (encoder + head)", forward_latency(model, n, options))
        for n in options.agents
    ]
    meanflow_ms, flow_matching_ms = training_steps(model, options)
    size = f"{options.train_scenes} scenes x {options.train_agents} agents"
    rows += [
        (f"train step, MeanFlow JVP ({size})", meanflow_ms),
        (f"train step, flow matching r = t, no JVP ({size})", flow_matching_ms),
    ]
    width = max(len(name) for name, _ in rows)
    print(f"{'measurement':<{width}}  {'ms':>9}")
    print("-" * (width + 11))
    for name, ms in rows:
        print(f"{name:<{width}}  {ms:9.2f}")
    print("-" * (width + 11))
    ratio = meanflow_ms / flow_matching_ms
    print(f"{'JVP / flow-matching step time (target <= 2.5x)':<{width}}  {ratio:8.2f}x")
    throughput = options.train_scenes / (meanflow_ms / 1e3)
    print(f"{'MeanFlow training throughput [scenes/s]':<{width}}  {throughput:9.1f}")
    agents = throughput * options.train_agents
    print(f"{'MeanFlow training throughput [agent plans/s]':<{width}}  {agents:9.1f}")
    return dict(rows)


if __name__ == "__main__":
    run_script("generator_speed.py", main)
