"""The report's PNG plots (matplotlib, Agg backend).

* ``cs_rs_T<interval>.png`` (``cs_rs.png`` for methods without a planning interval: rule-based
  traffic, replay): CS against RS, one panel per K (each table's own CS / RS),
  three panels a row; methods on (nearly) the same point are drawn side by side
  (:func:`spread`) so that none hides another;
* ``realism_vs_horizon_K<k>.png``: raw realism metrics (ORR, ADE, FDE, KDD, WOSAC)
  against the planning interval (the time between re-plans), one line per method;
* ``speed.png``: mean rollout time and mean planning-cycle time per method, at K=5,
  T=0.5 s when present (else the first table), log scale.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from policies.evaluation.table import Table  # noqa: E402

REALISM_PANELS = (
    ("orr", "ORR"), ("ade", "ADE [m]"), ("fde", "FDE [m]"), ("kdd", "KDD"), ("wosac", "WOSAC"),
)  # fmt: skip
SPEED_TABLE = (5, 0.5)
MARKERS = "osD^vP*Xh<>"
SPREAD = 0.05  # RS distance between markers of methods on (nearly) the same point


def _colors(labels: list[str]) -> dict[str, tuple]:
    cmap = plt.get_cmap("tab10")
    return {label: cmap(i % 10) for i, label in enumerate(labels)}


def _method_colors(tables: list[Table]) -> dict[str, tuple]:
    """One colour per method of ``tables``, in sorted order (the same in every plot)."""
    return _colors(sorted({label for table in tables for label in table.metrics}))


def _name(value: object) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def write_plots(tables: list[Table], out: Path) -> list[Path]:
    """Write every plot into ``out``; returns the files."""
    files = write_metric_plots(tables, out)
    return [*files, _speed(tables, _method_colors(tables), out / "speed.png")]


def write_metric_plots(tables: list[Table], out: Path) -> list[Path]:
    """Write the plots drawn from the metric tables alone (CS-RS, realism against the
    planning interval; not ``speed.png``) into ``out``; returns the files."""
    colors = _method_colors(tables)
    files = []
    for interval in dict.fromkeys(table.interval for table in tables):
        group = [t for t in tables if t.interval == interval]
        suffix = "" if interval is None else f"_T{_name(interval)}"
        files.append(_cs_rs(group, colors, out / f"cs_rs{suffix}.png"))
    for k in dict.fromkeys(table.k for table in tables):
        group = [t for t in tables if t.k == k]
        if len(group) > 1:  # a line over the planning intervals needs several of them
            files.append(_realism(group, colors, out / f"realism_vs_horizon_K{_name(k)}.png"))
    return files


def _cs_rs(tables: list[Table], colors: dict, path: Path) -> Path:
    columns = min(3, len(tables))
    rows = math.ceil(len(tables) / columns)
    width = max(4.6 * columns, 7.5)
    figure, axes = plt.subplots(rows, columns, figsize=(width, 4.2 * rows + 1.6), squeeze=False)
    labels = list(colors)
    for axis, table in zip(axes.flat, tables, strict=False):
        points = {
            label: (values["rs"], values["cs"])
            for label, values in table.metrics.items()
            if not (math.isnan(values["rs"]) or math.isnan(values["cs"]))
        }
        for label, (rs, cs) in spread(points).items():
            index = labels.index(label)
            marker = MARKERS[index % len(MARKERS)]
            axis.scatter(rs, cs, s=55, facecolors="none", edgecolors=colors[label],
                         linewidths=1.6, label=label, marker=marker)  # fmt: skip
        axis.set(title=table.title, xlabel="RS (realism)", ylabel="CS (safety-criticality)",
                 xlim=(-0.15, 1.15), ylim=(-0.1, 1.1))  # fmt: skip
        axis.grid(alpha=0.3)
    for axis in axes.flat[len(tables) :]:
        axis.set_visible(False)
    handles = {h.get_label(): h for a in axes.flat for h in a.collections}
    legend_columns = max(1, min(4, int(width // 3.2)))
    figure.legend(handles.values(), handles.keys(), loc="lower center", fontsize=9,
                  ncol=legend_columns, frameon=False)  # fmt: skip
    figure.suptitle(
        "CS against RS (up and right is better)\n"
        f"markers closer than {SPREAD} are drawn side by side, {SPREAD} apart in RS",
        fontsize=11,
    )
    legend_height = 0.25 * math.ceil(len(handles) / legend_columns) + 0.2  # [inch]
    figure.tight_layout(rect=(0, legend_height / figure.get_figheight(), 1, 1))
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def spread(points: dict[str, tuple[float, float]]) -> dict[str, tuple[float, float]]:
    """``points`` laid out so that no two markers are closer than ``SPREAD``.

    Markers closer than ``SPREAD`` (after layout) form a group, drawn side by side in x,
    ``SPREAD`` apart, in the order of their x (then of the labels), centred on the group's
    mean x, each at its own y; groups that then touch are merged and laid out again. The
    layout depends only on the points and the labels' order.
    """
    order = {label: i for i, label in enumerate(points)}
    groups = [[label] for label in points]
    while True:
        placed = {}
        for group in groups:
            group.sort(key=lambda label: (points[label][0], order[label]))
            centre = sum(points[label][0] for label in group) / len(group)
            for i, label in enumerate(group):
                placed[label] = (centre + (i - (len(group) - 1) / 2) * SPREAD, points[label][1])
        touching = next(
            ((a, b) for a, b in itertools.combinations(range(len(groups)), 2)
             if any(math.dist(placed[p], placed[q]) < SPREAD * (1 - 1e-9)
                    for p in groups[a] for q in groups[b])),
            None,
        )  # fmt: skip
        if touching is None:
            return {label: placed[label] for label in points}
        a, b = touching
        groups[a] += groups.pop(b)


def _realism(tables: list[Table], colors: dict, path: Path) -> Path:
    figure, axes = plt.subplots(2, 3, figsize=(13, 7.5))
    tables = sorted(tables, key=lambda t: t.interval or 0.0)
    for axis, (key, name) in zip(axes.flat, REALISM_PANELS, strict=False):
        for label in colors:
            points = [(t.interval or 0.0, t.metrics[label][key]) for t in tables
                      if label in t.metrics and not math.isnan(t.metrics[label][key])]  # fmt: skip
            if points:
                x, y = zip(*points, strict=True)
                index = list(colors).index(label)
                axis.plot(x, y, "-", marker=MARKERS[index % len(MARKERS)], color=colors[label],
                          label=label)  # fmt: skip
        axis.set(title=name, xlabel="planning interval T (re-plan every T s)")
        axis.grid(alpha=0.3)
    legend = axes.flat[-1]
    legend.axis("off")
    handles, names = axes.flat[0].get_legend_handles_labels()
    legend.legend(handles, names, loc="center", fontsize=10, frameon=False)
    figure.suptitle(f"Realism against the planning interval, K={_name(tables[0].k)}")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def _speed(tables: list[Table], colors: dict, path: Path) -> Path:
    table = next((t for t in tables if (t.k, t.interval) == SPEED_TABLE), tables[0])
    labels = list(table.timing)
    figure, axes = plt.subplots(1, 2, figsize=(max(7, 1.6 * len(labels)), 3.8))
    for axis, (key, name) in zip(
        axes,
        (("per_scene_s", "rollout time per scene [s]"), ("cycle_ms", "planning cycle [ms]")),
        strict=True,
    ):
        values = [table.timing[label][key] for label in labels]
        bars = axis.bar(labels, values, color=[colors[label] for label in labels])
        axis.bar_label(bars, labels=[f"{v:.3g}" for v in values], fontsize=8)
        axis.set(title=name, yscale="log")
        axis.tick_params(axis="x", labelsize=8)
        plt.setp(axis.get_xticklabels(), rotation=30, ha="right")
        axis.grid(alpha=0.3, axis="y")
    figure.suptitle(f"Speed, {table.title} (same run, same machine)")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path
