"""Does the RiskFlow adversary make the IDM ego fail, without driving off the road?

Runs every configuration (default: K=5 and K=0, the unguided generator) closed loop for
10 s on the first ``--scenes`` shipped evaluation scenes, with the IDM ego planner, and
prints collision and off-road rates with 95% confidence intervals (Wilson for rates,
bootstrap for means) plus the ratios of each K to K=0::

    python benchmarks/adversary_quality.py --scenes 50 --ks 5,0 --target ego

The episode ends early when the ego collides (the default ``EnvConfig``), as in a
stress test; ``--full-episodes`` runs every episode for 10 s instead, so that off-road
rates are compared over the same exposure. The adversary runs with the library's
defaults: the realistic base (20 avoidance steps, holding at rest at 4 m, blending first
over 15 steps), the map term weighted 20, the separation term between the guided
vehicles weighted 100 and the target's guidance step (0.1 with ``--target ego``, 0.01
with ``others``; docs/REALISM.md, rounds 8-18 and 26);
``--avoid-steps 0 --hold-distance 0 --lambda-map 1 --lambda-sep 0 --step-size 0.1
--no-stitch-first`` is the raw base of ``riskflow-eval``'s ``riskflow-plain``;
``--stitch-steps N`` sets the blend and ``--guidance-horizon N`` the steps of the plan
that the adversarial term pulls (docs/REALISM.md, round 30). ``--out`` receives
``quality.json`` with the summaries and every scene's metrics.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from policies.dataclass_cli import parse_dataclass
from policies.harness import ClosedLoop, EpisodeRecord, mean_summary, summarize
from policies.learned.adversary_config import AdversaryConfig
from policies.learned.checkpoint import load_generator
from policies.learned.plan_avoidance import DEFAULT_AVOID_STEPS
from policies.learned.plan_stitching import resolve_stitch_steps
from policies.planners import IDMPlanner
from policies.riskflow import RiskFlowAdversary
from policies.riskflow.guidance import GuidanceConfig
from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import shipped_bank
from riskflow_env.view import SceneView

ROWS = {
    "collision_rate": "episodes with any collision",
    "ego_collision_rate": "episodes with an ego collision",
    "orr_centroid": "agent-steps, centre off road",
    "orr_footprint": "agent-steps, footprint off road",
    "orr_footprint_guided": "agent-steps of guided vehicles, footprint off road",
    "min_distance_to_ego": "least ego separation [m]",
    "planning_time_ms": "planning cycle [ms]",
}


@dataclass(frozen=True)
class Options:
    """Quality check of the adversary."""

    scenes: int = 50
    """number of shipped evaluation scenes (the first ones)"""
    ks: str = "5,0"
    """comma-separated K values to compare (ints or 'all'); the last one is the reference"""
    target: str = "ego"
    """guidance target: 'ego' (stress test) or 'others' (the paper's)"""
    planning_interval: float = 0.5
    """[s] replanning period"""
    seed: int = 0
    """adversary noise seed"""
    full_episodes: bool = False
    """run every episode for the full 10 s (no termination on collision or off-road)"""
    checkpoint: str | None = None
    """generator checkpoint; default: the shipped one"""
    avoid_steps: int = DEFAULT_AVOID_STEPS
    """avoidance steps on the base plans (0: off)"""
    hold_distance: float = AdversaryConfig.hold_distance
    """[m] a vehicle at rest whose plan moves it less keeps its brake on (0: off)"""
    lambda_map: float = AdversaryConfig.lambda_map
    """weight of the guidance's map term"""
    step_size: float | None = GuidanceConfig.step_size
    """guidance step size (Adam's learning rate, normalised action units); default: the
    target's (0.01 with 'others', 0.1 with 'ego')"""
    optimizer: str = GuidanceConfig.optimizer
    """guidance steps: 'adam' (per coordinate), 'adam-plan' (one second moment per guided
    plan) or 'gradient' (plain steps)"""
    lambda_sep: float = GuidanceConfig.lambda_sep
    """weight of the separation term between the guided vehicles (0: off, the paper's
    objective)"""
    guidance_horizon: int | None = AdversaryConfig.guidance_horizon
    """[steps] guidance horizon T_g of the adversarial term; default: the whole plan"""
    stitch_steps: int | None = AdversaryConfig.stitch_steps
    """[steps] blend of a new plan into the executed one (default: 15 blending first, 5
    after; 0: switch at once)"""
    stitch_first: bool = True
    """blend the base plans before the avoidance steps (RiskFlowAdversary stitch_first)"""
    out: str = "outputs/adversary_quality"
    """output directory"""


class GuidedSteps:
    """The adversary, recording after each ``act`` the names it guides (its current
    cycle's ``A_c``); everything else is the adversary's."""

    def __init__(self, adversary: RiskFlowAdversary) -> None:
        self.adversary = adversary
        self.guided: list[tuple[str, ...]] = []

    def __getattr__(self, name: str):
        return getattr(self.adversary, name)

    def reset(self, view: SceneView) -> None:
        self.guided = []
        self.adversary.reset(view)

    def act(self, view: SceneView) -> dict[str, np.ndarray]:
        actions = self.adversary.act(view)
        self.guided.append(self.adversary.controllable_names)
        return actions


def guided_footprint_rate(record: EpisodeRecord, guided: list[tuple[str, ...]]) -> float:
    """Share of the guided vehicles' agent-steps with a footprint point off the road: the
    state after each step counts for the vehicles guided when its action was planned
    (NaN when nobody was guided)."""
    mask = np.zeros_like(record.in_scene)
    for step, names in enumerate(guided):
        mask[:, step + 1] = np.isin(record.agent_names, names)
    mask &= record.in_scene
    return float(record.offroad_footprint[mask].mean()) if mask.any() else float("nan")


def _json(value: float) -> float | None:
    return None if math.isnan(value) else value


def run(options: Options) -> dict[str, dict]:
    """Summaries per K (``{k: {metric: {value, low, high, n}}}``)."""
    generator, normalizer, _ = load_generator(options.checkpoint)
    bank = shipped_bank("eval")
    scenes = [bank[i] for i in range(min(options.scenes, len(bank)))]
    results: dict[str, dict] = {}
    for k in options.ks.split(","):
        adversary = RiskFlowAdversary(
            k=k if k == "all" else int(k),
            planning_interval=options.planning_interval,
            target=options.target,
            seed=options.seed,
            generator=generator,
            normalizer=normalizer,
            avoid_steps=options.avoid_steps,
            hold_distance=options.hold_distance,
            lambda_map=options.lambda_map,
            step_size=options.step_size,
            optimizer=options.optimizer,
            lambda_sep=options.lambda_sep,
            guidance_horizon=options.guidance_horizon,
            stitch_steps=options.stitch_steps,
            stitch_first=options.stitch_first,
        )
        config = (
            EnvConfig(terminate_on_collision="none", terminate_on_offroad="none")
            if options.full_episodes
            else None
        )
        recorder, guided = GuidedSteps(adversary), []
        with ClosedLoop(IDMPlanner(), recorder, config=config) as loop:
            for scenario in tqdm(scenes, desc=f"K={k}"):
                record = loop.run(scenario)
                guided.append(guided_footprint_rate(record, recorder.guided))
                record.metrics["orr_footprint_guided"] = _json(guided[-1])
            summary = summarize(loop.records)
            summary["orr_footprint_guided"] = mean_summary(guided)
            results[k] = {
                "summary": summary,
                "scenes": [record.metrics for record in loop.records],
            }
    return results


def table(results: dict[str, dict]) -> str:
    """Markdown table: one column per K, the last K as reference for the ratios."""
    ks = list(results)
    reference = results[ks[-1]]["summary"]
    header = "| metric | " + " | ".join(f"K={k}" for k in ks) + " | ratio to K=" + ks[-1] + " |"
    lines = [header, "|" + " --- |" * (len(ks) + 2)]
    for name, label in ROWS.items():
        cells = []
        for k in ks:
            entry = results[k]["summary"][name]
            value = entry["value"]
            if value is None:
                cells.append("n/a")
            elif entry["low"] is None:
                cells.append(f"{value:.3f}")
            else:
                cells.append(f"{value:.3f} [{entry['low']:.3f}, {entry['high']:.3f}]")
        first, base = results[ks[0]]["summary"][name]["value"], reference[name]["value"]
        ratio = f"{first / base:.2f}x" if first is not None and base else "n/a"
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {ratio} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    options = parse_dataclass(Options, argv, prog="adversary_quality")
    results = run(options)
    out = Path(options.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "quality.json").write_text(json.dumps({"options": vars(options), **results}, indent=1))
    ending = "full 10 s" if options.full_episodes else "ends at an ego collision"
    stitch = resolve_stitch_steps(options.stitch_steps, options.stitch_first)
    step_size = GuidanceConfig(
        step_size=options.step_size, target=options.target
    ).resolved_step_size
    base = (
        f"avoid_steps={options.avoid_steps}, hold_distance={options.hold_distance:g}, "
        f"lambda_map={options.lambda_map:g}, step_size={step_size:g}, "
        f"optimizer={options.optimizer}, "
        f"lambda_sep={options.lambda_sep:g}, guidance_horizon={options.guidance_horizon}, "
        f"stitch_steps={stitch}, "
        f"stitch_first={options.stitch_first}"
    )
    print(f"{options.scenes} scenes, IDM ego, target={options.target}, episodes: {ending}, {base}")
    print(table(results))


if __name__ == "__main__":
    main()
