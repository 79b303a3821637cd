"""Tables and plots of :func:`policies.rl.evaluation.summarize_ego` summaries.

``summaries`` everywhere is ``{(planner, traffic): {metric: {"value", "low", "high",
"n"}}}``; the Markdown table has one row per (planner, traffic) and one column per metric
(``value [low, high]``); the plot one panel per metric, one group of bars per traffic,
one bar per planner, with the 95% interval as error bars.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from policies.learned.ranking import MIN_ATTACK_SPEED

METRIC_LABELS = {
    "ego_collision_rate": "ego collision rate",
    "ego_offroad_rate": "ego off-road rate",
    "ego_failure_rate": "collision or off-road",
    "avoidable_failure_rate": "avoidable collision",
    "progress": "progress [m]",
    "ego_collisions_per_km": "ego collisions per km",
    "slow_ego_share": f"ego steps below {MIN_ATTACK_SPEED:g} m/s",
    "time_to_first_ego_collision": "time to 1st ego collision [s]",
}

COUNTS = ("n", "trained", "untrained", "trained_only", "untrained_only")
MISSING = {"value": None}  # a metric a summary lacks (one combined from an older results.json)

Summaries = Mapping[tuple[str, str], Mapping[str, Mapping[str, Any]]]


def format_entry(entry: Mapping[str, Any], digits: int = 3) -> str:
    """``value [low, high]`` (``–`` where undefined)."""

    def number(x: float | None) -> str:
        return "–" if x is None else f"{x:.{digits}f}"

    if entry["value"] is None:
        return "–"
    if entry["low"] is None:
        return number(entry["value"])
    return f"{number(entry['value'])} [{number(entry['low'])}, {number(entry['high'])}]"


def markdown_table(summaries: Summaries, metrics: tuple[str, ...] = tuple(METRIC_LABELS)) -> str:
    """One row per (planner, traffic), ``value [95% interval]`` per metric, episodes last."""
    header = ["ego planner", "traffic", *(METRIC_LABELS[m] for m in metrics), "episodes"]
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    for (planner, traffic), summary in summaries.items():
        digits = {"progress": 1, "ego_collisions_per_km": 2, "time_to_first_ego_collision": 2}
        cells = [format_entry(summary.get(m, MISSING), digits.get(m, 3)) for m in metrics]
        count = summary[metrics[0]]["n"]
        lines.append("| " + " | ".join([planner, traffic, *cells, str(count)]) + " |")
    return "\n".join(lines)


def paired_table(rows: list[Mapping[str, Any]], reference: str = "untrained") -> str:
    """Trained vs ``reference`` on paired episodes (:func:`~policies.rl.paired.paired_counts`
    rows, one per run, traffic and outcome, with ``reference``'s counts as the
    ``untrained`` ones: the untrained policy, or a baseline planner), per run and pooled
    over the runs ("all": the counts summed), with
    :func:`~policies.statistics.paired_difference` for each."""
    from policies.statistics import paired_difference

    table: dict[tuple, dict[str, Any]] = {}
    for row in rows:
        table[row["planner"], row["traffic"], row["metric"], row["run"]] = row
        total = table.setdefault((row["planner"], row["traffic"], row["metric"], "all"), {})
        for name in COUNTS:
            total[name] = total.get(name, 0) + row[name]
    runs = Counter(key[:3] for key in table if key[3] != "all")
    header = ["ego", "run", "traffic", "outcome", reference, "trained"]
    header += [
        f"trained - {reference} [95% CI]",
        f"only {reference} / only trained",
        "McNemar p",
        "episodes",
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    for (planner, traffic, metric, run), counts in sorted(table.items(), key=_paired_order):
        if run == "all" and runs[planner, traffic, metric] < 2:
            continue  # one run: its row is the pooled row
        d = paired_difference(counts)
        n = d["n"]
        cells = [planner, run, traffic, METRIC_LABELS[metric]]
        cells += [f"{d['untrained'] / n:.3f}", f"{d['trained'] / n:.3f}"]
        cells += [f"{d['difference']:+.3f} [{d['low']:+.3f}, {d['high']:+.3f}]"]
        cells += [f"{d['untrained_only']} / {d['trained_only']}", f"{d['p_value']:.2g}", str(n)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _paired_order(item: tuple) -> tuple:
    (planner, traffic, metric, run), _ = item
    return planner, traffic, metric, run == "all", run


def plot_summaries(
    summaries: Summaries,
    path: str | os.PathLike,
    metrics: tuple[str, ...] = ("ego_collision_rate", "ego_offroad_rate", "progress"),
) -> None:
    """Bar chart with 95% intervals, saved to ``path`` (PNG/SVG/PDF by extension)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    planners = list(dict.fromkeys(p for p, _ in summaries))
    traffics = list(dict.fromkeys(t for _, t in summaries))
    figure, axes = plt.subplots(1, len(metrics), figsize=(4.2 * len(metrics), 3.6), squeeze=False)
    width = 0.8 / max(len(planners), 1)
    palette = plt.get_cmap("tab10" if len(planners) <= 10 else "tab20")
    for axis, metric in zip(axes[0], metrics, strict=True):
        for index, planner in enumerate(planners):
            values, errors = [], [[], []]
            for traffic in traffics:
                entry = summaries.get((planner, traffic), {}).get(metric)
                value = np.nan if entry is None or entry["value"] is None else entry["value"]
                low = value if entry is None or entry["low"] is None else entry["low"]
                high = value if entry is None or entry["high"] is None else entry["high"]
                values.append(value)
                errors[0].append(value - low)
                errors[1].append(high - value)
            positions = np.arange(len(traffics)) + (index - (len(planners) - 1) / 2) * width
            color = palette(index % palette.N)
            axis.bar(positions, values, width, yerr=errors, capsize=3, label=planner, color=color)
        axis.set_xticks(np.arange(len(traffics)), traffics)
        axis.set_title(METRIC_LABELS[metric])
        axis.grid(axis="y", alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="lower center", ncol=min(len(planners), 7), fontsize="small")
    figure.tight_layout(rect=(0, 0.08, 1, 1))
    figure.savefig(path, dpi=120)
    plt.close(figure)


def plot_training(
    runs: Mapping[str, str | os.PathLike], path: str | os.PathLike, window: int = 8
) -> None:
    """Training curves of ``train_ego_ppo.py`` runs: the share of training episodes that
    ended in an ego collision and in an off-road excursion against the env decisions.
    Every rollout's rate is a dot; the line is their trailing mean over the last ``window``
    rollouts (fewer at the start), so a short run shows what it has. A run
    without a ``progress.csv`` or without a finished episode yet is named on the panel.

    Args:
        runs: label -> run folder (with ``progress.csv``).
        path: the image (PNG/SVG/PDF by extension).
        window: rollouts averaged per point of the line.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    columns = {
        "ego collision": "rollout/ego_collision_rate",
        "ego off-road": "rollout/ego_offroad_rate",
    }
    figure, axes = plt.subplots(1, len(columns), figsize=(5.0 * len(columns), 3.4), squeeze=False)
    empty = []
    for index, (label, run) in enumerate(runs.items()):
        rows = _progress_rows(Path(run) / "progress.csv", columns["ego collision"])
        if not rows:
            empty.append(label)
            continue
        steps = np.array([float(row["time/total_timesteps"]) for row in rows])
        color = plt.get_cmap("tab10")(index % 10)
        for axis, column in zip(axes[0], columns.values(), strict=True):
            rate = np.array([float(row[column]) for row in rows])
            smooth = [rate[max(0, i + 1 - window) : i + 1].mean() for i in range(len(rate))]
            axis.plot(steps, rate, ".", color=color, alpha=0.35, markersize=4)
            axis.plot(steps, smooth, "-o" if len(rate) == 1 else "-", color=color,
                      label=f"{label} ({len(rate)} rollouts)", markersize=4)  # fmt: skip
    for axis, title in zip(axes[0], columns, strict=True):
        axis.set_title(f"{title} (share of training episodes)")
        axis.set_xlabel("policy decisions")
        axis.set_ylim(-0.03, 1.03)
        axis.set_xlim(left=0)
        axis.grid(alpha=0.3)
    if empty:
        axes[0][0].text(0.5, 0.5, "no finished training episode yet:\n" + ", ".join(empty),
                        ha="center", va="center", transform=axes[0][0].transAxes)  # fmt: skip
    if len(empty) < len(runs):
        axes[0][0].legend(fontsize="small")
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def _progress_rows(path: Path, column: str) -> list[dict[str, str]]:
    """The rows of an SB3 ``progress.csv`` with a value in ``column`` ([] without the file)."""
    import csv

    if not path.is_file():
        return []
    with open(path, newline="", encoding="utf-8") as file:
        return [row for row in csv.DictReader(file) if row.get(column)]
