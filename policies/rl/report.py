"""Tables and plots of :func:`policies.rl.evaluation.summarize_ego` summaries.

``summaries`` everywhere is ``{(planner, traffic): {metric: {"value", "low", "high",
"n"}}}``; the Markdown table has one row per (planner, traffic) and one column per metric
(``value [low, high]``); the plot one panel per metric, one group of bars per traffic,
one bar per planner, with the 95% interval as error bars.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

METRIC_LABELS = {
    "ego_collision_rate": "ego collision rate",
    "ego_offroad_rate": "ego off-road rate",
    "ego_failure_rate": "collision or off-road",
    "progress": "progress [m]",
    "time_to_first_ego_collision": "time to 1st ego collision [s]",
}

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
        digits = {"progress": 1, "time_to_first_ego_collision": 2}
        cells = [format_entry(summary[m], digits.get(m, 3)) for m in metrics]
        count = summary[metrics[0]]["n"]
        lines.append("| " + " | ".join([planner, traffic, *cells, str(count)]) + " |")
    return "\n".join(lines)


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
            axis.bar(positions, values, width, yerr=errors, capsize=3, label=planner)
        axis.set_xticks(np.arange(len(traffics)), traffics)
        axis.set_title(METRIC_LABELS[metric])
        axis.grid(axis="y", alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="lower center", ncol=min(len(planners), 7), fontsize="small")
    figure.tight_layout(rect=(0, 0.08, 1, 1))
    figure.savefig(path, dpi=120)
    plt.close(figure)
