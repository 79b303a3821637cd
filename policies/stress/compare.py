"""``riskflow-stress compare A B``: two planners on the same scenes and seeds, paired.

Both planners face every (scene, seed) episode (a full stress test each, in
``<out>/a-<name>/`` and ``<out>/b-<name>/``); an episode's outcome for A and for B is one
pair. Per outcome (an ego collision; an ego collision shown avoidable) the table gives each
planner's rate, the difference A - B with Agresti and Min's interval for matched pairs and
the exact McNemar test on the discordant pairs (:func:`policies.statistics.paired_difference`):
pairing removes the between-scene variance, so it separates planners that two overlapping
Wilson intervals cannot. The ego's progress and its collisions per kilometre are the
counter-metrics (a planner that stands still is rarely hit). ``compare.json`` and
``compare.md`` hold the table.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from policies.planners import EgoPlanner
from policies.statistics import paired_difference
from policies.stress.planner_spec import load_planner
from policies.stress.stress_test import StressResult, riskflow_stress
from riskflow_env.atomic_files import write_text
from riskflow_env.scenarios import Scenario

OUTCOMES = {
    "ego_collided": "ego collision rate",
    "avoidable_failure": "avoidable-failure rate",
}


def compare(
    a: str | EgoPlanner,
    b: str | EgoPlanner,
    scenes: int | Sequence[Scenario] = 20,
    seeds: Sequence[int] = (0,),
    *,
    out: str | os.PathLike | None = None,
    **options: Any,
) -> dict[str, Any]:
    """Stress-test planners ``a`` and ``b`` on the same episodes; the paired table.

    Args:
        a, b: the planners (objects or specs, as :func:`riskflow_stress` takes them).
        scenes, seeds: the episodes, as :func:`riskflow_stress` takes them.
        out: folder of both runs and ``compare.json`` / ``compare.md``; None: no files.
        **options: further :func:`riskflow_stress` arguments (``k``, ``steps``, ...).

    Returns:
        ``{"a", "b", "episodes", "rows"}``: the two planners' names, the number of paired
        episodes, and a row per outcome (:data:`OUTCOMES`) and per counter-metric; with
        ``out``, also ``"folders"``: the runs' sub-folders of ``out`` (``{"a": "a-idm",
        ...}``; the sub-folders of earlier comparisons in the same ``out`` are left as they
        are).
    """
    folder = None if out is None else Path(out)
    for letter, planner in (("a", a), ("b", b)):  # a bad b fails before a's run
        if isinstance(planner, str):
            load_planner(planner, argument=letter)  # the file or module, and its object
    runs, names = [], {}
    for letter, planner in (("a", a), ("b", b)):
        names[letter] = f"{letter}-{_safe(_label(planner))}"
        sub = None if folder is None else folder / names[letter]
        runs.append(riskflow_stress(planner, scenes, seeds, out=sub, **options))
    table = paired_table(*runs)
    if folder is not None:  # which sub-folders are this comparison's, in a reused --out
        table["folders"] = names
        write_text(folder / "compare.json", json.dumps(table, indent=2) + "\n")
        write_text(folder / "compare.md", markdown(table) + "\n")
    return table


def paired_table(a: StressResult, b: StressResult) -> dict[str, Any]:
    """The paired comparison of two runs of the same episodes (module docstring)."""
    rows_a, rows_b = a.summary["per_episode"], b.summary["per_episode"]
    if [(r["scene"], r["seed"]) for r in rows_a] != [(r["scene"], r["seed"]) for r in rows_b]:
        raise ValueError("a and b must be runs of the same scenes and seeds, in the same order")
    rows = []
    for key, label in OUTCOMES.items():
        hit_a = np.array([r[key] for r in rows_a], dtype=bool)
        hit_b = np.array([r[key] for r in rows_b], dtype=bool)
        test = paired_difference(
            {
                "n": len(hit_a),
                "trained": int(hit_a.sum()),
                "untrained": int(hit_b.sum()),
                "trained_only": int((hit_a & ~hit_b).sum()),
                "untrained_only": int((~hit_a & hit_b).sum()),
            }
        )
        rows.append(
            {
                "outcome": label,
                "a": a.summary[_SUMMARY[key]],
                "b": b.summary[_SUMMARY[key]],
                "a_only": test["trained_only"],
                "b_only": test["untrained_only"],
                "difference": test["difference"],
                "low": test["low"],
                "high": test["high"],
                "p_value": test["p_value"],
            }
        )
    for key, label in COUNTER_METRICS.items():
        if key in a.summary and key in b.summary:  # older summaries lack the rate per km
            rows.append({"outcome": label, "a": a.summary[key], "b": b.summary[key]})
    return {
        "a": a.summary["planner"],
        "b": b.summary["planner"],
        "episodes": len(rows_a),
        "rows": rows,
    }


_SUMMARY = {"ego_collided": "ego_collision_rate", "avoidable_failure": "avoidable_failure_rate"}
COUNTER_METRICS = {
    "progress": "ego progress [m] (counter-metric)",
    "ego_collisions_per_km": "ego collisions per km (counter-metric)",
}
_DIGITS = {COUNTER_METRICS["ego_collisions_per_km"]: 2}  # other values: 1 decimal


def markdown(table: dict[str, Any]) -> str:
    """The table in Markdown (``compare.md``, and what the command prints)."""
    folders = table.get("folders")
    lines = [
        f"A = {table['a']}, B = {table['b']}, {table['episodes']} paired episodes",
        *([f"runs: {folders['a']}/, {folders['b']}/"] if folders else []),
        "",
        "| outcome | A | B | A - B [95% CI] | A only / B only | McNemar p |",
        "|---|---|---|---|---|---|",
    ]
    for row in table["rows"]:
        percent = "difference" in row
        digits = _DIGITS.get(row["outcome"], 1)
        a, b = (_value(row[side], percent, digits) for side in ("a", "b"))
        if not percent:
            lines.append(f"| {row['outcome']} | {a} | {b} | | | |")
            continue
        difference = "n/a"
        if row["difference"] is not None:
            difference = (
                f"{100 * row['difference']:+.1f} pts "
                f"[{100 * row['low']:+.1f}, {100 * row['high']:+.1f}]"
            )
        lines.append(
            f"| {row['outcome']} | {a} | {b} | {difference} | {row['a_only']} / "
            f"{row['b_only']} | {row['p_value']:.3g} |"
        )
    return "\n".join(lines)


def _value(entry: dict[str, Any], percent: bool, digits: int = 1) -> str:
    value = entry["value"]
    if value is None:
        return "n/a"
    return f"{100 * value:.1f}%" if percent else f"{value:.{digits}f}"


def _label(planner: str | EgoPlanner) -> str:
    if isinstance(planner, str):
        return planner.rpartition(":")[2] or planner
    return getattr(planner, "__name__", None) or type(planner).__name__


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name)


__all__ = ["OUTCOMES", "compare", "markdown", "paired_table"]
