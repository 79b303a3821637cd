"""The report's PNG plots (matplotlib, Agg backend).

* ``cs_rs_T<interval>.png``: CS against RS, one panel per K (each table's own CS / RS);
* ``realism_vs_horizon_K<k>.png``: raw realism metrics (ORR, ADE, FDE, KDD, WOSAC)
  against the planning interval, one line per method;
* ``speed.png``: mean rollout time and mean planning-cycle time per method, at K=5,
  T=0.5 s when present (else the first table), log scale.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from policies.evaluation.report import Table  # noqa: E402

REALISM_PANELS = (
    ("orr", "ORR"), ("ade", "ADE [m]"), ("fde", "FDE [m]"), ("kdd", "KDD"), ("wosac", "WOSAC"),
)  # fmt: skip
SPEED_TABLE = (5, 0.5)
MARKERS = "osD^vP*Xh<>"


def _colors(labels: list[str]) -> dict[str, tuple]:
    cmap = plt.get_cmap("tab10")
    return {label: cmap(i % 10) for i, label in enumerate(labels)}


def _name(value: object) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def write_plots(tables: list[Table], out: Path) -> list[Path]:
    """Write every plot into ``out``; returns the files."""
    labels = sorted({label for table in tables for label in table.metrics})
    colors = _colors(labels)
    files = []
    for interval in dict.fromkeys(table.interval for table in tables):
        group = [t for t in tables if t.interval == interval]
        files.append(_cs_rs(group, colors, out / f"cs_rs_T{_name(interval)}.png"))
    for k in dict.fromkeys(table.k for table in tables):
        group = [t for t in tables if t.k == k]
        files.append(_realism(group, colors, out / f"realism_vs_horizon_K{_name(k)}.png"))
    files.append(_speed(tables, colors, out / "speed.png"))
    return files


def _cs_rs(tables: list[Table], colors: dict, path: Path) -> Path:
    figure, axes = plt.subplots(1, len(tables), figsize=(4 * len(tables) + 2.5, 4), squeeze=False)
    for axis, table in zip(axes[0], tables, strict=True):
        for label, values in table.metrics.items():
            rs, cs = values["rs"], values["cs"]
            if math.isnan(rs) or math.isnan(cs):
                continue
            index = list(colors).index(label)
            axis.scatter(rs, cs, color=colors[label], s=60, alpha=0.85, label=label,
                         marker=MARKERS[index % len(MARKERS)])  # fmt: skip
        axis.set(title=table.title, xlabel="RS (realism)", ylabel="CS (safety-criticality)",
                 xlim=(-0.1, 1.15), ylim=(-0.1, 1.15))  # fmt: skip
        axis.grid(alpha=0.3)
    handles = {h.get_label(): h for a in axes[0] for h in a.collections}
    figure.legend(handles.values(), handles.keys(), loc="center right", fontsize=8)
    figure.suptitle("CS against RS (up and right is better)")
    figure.tight_layout(rect=(0, 0, 0.8, 1))
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def _realism(tables: list[Table], colors: dict, path: Path) -> Path:
    figure, axes = plt.subplots(1, len(REALISM_PANELS), figsize=(3.3 * len(REALISM_PANELS), 3.4))
    tables = sorted(tables, key=lambda t: t.interval or 0.0)
    for axis, (key, name) in zip(axes, REALISM_PANELS, strict=True):
        for label in colors:
            points = [(t.interval or 0.0, t.metrics[label][key]) for t in tables
                      if label in t.metrics and not math.isnan(t.metrics[label][key])]  # fmt: skip
            if points:
                x, y = zip(*points, strict=True)
                axis.plot(x, y, "o-", color=colors[label], label=label)
        axis.set(title=name, xlabel="planning interval [s]")
        axis.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    figure.suptitle(f"Realism against the planning horizon, K={_name(tables[0].k)}")
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
