"""Does the RiskFlow adversary make the IDM ego fail, without driving off the road?

Runs ``riskflow`` (the library's default, :func:`policies.registry.build_policy` with no
options: the realistic base) at every K of ``--ks`` (default K=5 and K=0, the unguided
generator) closed loop for 10 s on the first ``--scenes`` shipped evaluation scenes, with
the IDM ego planner, and prints collision and off-road rates with 95% confidence
intervals (Wilson for rates, bootstrap for means) plus the ratio of the first K to the
last::

    python benchmarks/adversary_quality.py --scenes 50 --ks 5,0 --target ego [--raw]

``--raw`` adds ``riskflow-raw`` (the raw generator: no avoidance steps, no holding at
rest) at the same K values, next to the default, with its own ratio. ``--set key=value``
gives the policies options as ``riskflow-eval --set`` does (e.g. ``step_size=0.03``,
``guidance_horizon=20``). The episode ends early when the ego collides (the default
``EnvConfig``), as in a stress test; ``--full-episodes`` runs every episode for 10 s
instead, so that off-road rates are compared over the same exposure. ``--out`` receives
``quality.json`` with the summaries and every scene's metrics.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from methods import make_policy, with_raw
from tqdm import tqdm

from policies.cli_inputs import check_seeds
from policies.dataclass_cli import check_at_least, check_choices, parse_dataclass
from policies.evaluation.options import parse_k, scene_names
from policies.harness import ClosedLoop, EpisodeRecord, mean_summary, summarize
from policies.learned.guidance_losses import TARGETS
from policies.planners import IDMPlanner
from policies.registry import method_options
from riskflow_env.cli_errors import run_script
from riskflow_env.config import EnvConfig
from riskflow_env.folder_lock import check_output_folder
from riskflow_env.scenarios import shipped_bank
from riskflow_env.view import ScenePolicy, SceneView

METHOD = "riskflow"
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
    seed: int = 0
    """adversary noise seed"""
    full_episodes: bool = False
    """run every episode for the full 10 s (no termination on collision or off-road)"""
    checkpoint: str | None = None
    """generator checkpoint; default: the shipped one"""
    raw: bool = False
    """also riskflow-raw (the raw generator, without the rule layer) at every K"""
    overrides: tuple[str, ...] = field(default=(), metadata={"flag": "--set"})
    """policy options key=value (riskflow-eval --set), e.g. step_size=0.03"""
    out: str = "outputs/adversary_quality"
    """output directory"""

    def __post_init__(self) -> None:
        check_at_least(self, {"scenes": 1})
        check_seeds((self.seed,), "--seed")
        check_choices(self, {"target": TARGETS})
        scene_names(None, self.scenes)  # --scenes beyond the shipped bank: named
        check_output_folder(self.out, "--out")
        ks = [parse_k(k) for k in self.ks.split(",")]
        if len(set(ks)) < len(ks):
            raise ValueError(f"--ks: each K once, got {self.ks}")
        method_options(with_raw((METHOD,), self.raw), self.overrides, None)

    @property
    def k_values(self) -> list[int | str]:
        """The K values of ``--ks``."""
        return [parse_k(k) for k in self.ks.split(",")]


class GuidedSteps:
    """The adversary, recording after each ``act`` the names it guides (its current
    cycle's ``A_c``); everything else is the adversary's."""

    def __init__(self, adversary: ScenePolicy) -> None:
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
    """Summaries per column (``{"K=5": {"summary": {metric: {value, low, high, n}},
    "scenes": [...]}}``; raw columns are labelled ``"K=5 raw"``)."""
    bank = shipped_bank("eval")
    scenes = [bank[i] for i in range(min(options.scenes, len(bank)))]
    methods = with_raw((METHOD,), options.raw)
    settings = method_options(methods, options.overrides, None)
    model = {} if options.checkpoint is None else {"checkpoint": options.checkpoint}
    config = (
        EnvConfig(terminate_on_collision="none", terminate_on_offroad="none")
        if options.full_episodes
        else None
    )
    results: dict[str, dict] = {}
    for method in methods:
        for k in options.k_values:
            adversary = make_policy(
                method, settings[method] | model, k=k, target=options.target, seed=options.seed
            )
            label = column(method, k)
            recorder, guided = GuidedSteps(adversary), []
            with ClosedLoop(IDMPlanner(), recorder, config=config) as loop:
                for scenario in tqdm(scenes, desc=label):
                    record = loop.run(scenario)
                    guided.append(guided_footprint_rate(record, recorder.guided))
                    record.metrics["orr_footprint_guided"] = _json(guided[-1])
                summary = summarize(loop.records)
                summary["orr_footprint_guided"] = mean_summary(guided)
                results[label] = {
                    "method": method,
                    "summary": summary,
                    "scenes": [record.metrics for record in loop.records],
                }
    return results


def column(method: str, k: int | str) -> str:
    """A column's label: ``K=5`` for the default method, ``K=5 raw`` for its raw variant."""
    return f"K={k}" if method == METHOD else f"K={k} raw"


def _cell(entry: dict) -> str:
    value = entry["value"]
    if value is None:
        return "n/a"
    if entry["low"] is None:
        return f"{value:.3f}"
    return f"{value:.3f} [{entry['low']:.3f}, {entry['high']:.3f}]"


def table(results: dict[str, dict]) -> str:
    """Markdown table: one column per K (and method), then per method the ratio of its
    first K to its last."""
    labels = list(results)
    groups: dict[str, list[str]] = {}
    for label in labels:
        groups.setdefault(results[label]["method"], []).append(label)
    ratios = [f"{group[0]} / {group[-1]}" for group in groups.values()]
    lines = ["| metric | " + " | ".join(labels + ratios) + " |"]
    lines.append("|" + " --- |" * (len(labels) + len(ratios) + 1))
    for name, text in ROWS.items():
        cells = [_cell(results[label]["summary"][name]) for label in labels]
        for group in groups.values():
            first = results[group[0]]["summary"][name]["value"]
            base = results[group[-1]]["summary"][name]["value"]
            cells.append(f"{first / base:.2f}x" if first is not None and base else "n/a")
        lines.append(f"| {text} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


PROG = "adversary_quality.py"  # the name in usage and error lines


def main(argv: list[str] | None = None) -> dict[str, dict]:
    """Run, write ``quality.json``, print the table; returns :func:`run`'s result."""
    options = parse_dataclass(Options, argv, prog=PROG, debug=True)
    results = run(options)
    out = Path(options.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "quality.json").write_text(json.dumps({"options": vars(options), **results}, indent=1))
    ending = "full 10 s" if options.full_episodes else "ends at an ego collision"
    methods = ", ".join(with_raw((METHOD,), options.raw))
    given = ", ".join(options.overrides) or "the library's defaults"
    print(
        f"{options.scenes} scenes, IDM ego, target={options.target}, episodes: {ending}; "
        f"{methods}: {given}"
    )
    print(table(results))
    return results


if __name__ == "__main__":
    run_script(PROG, main)
