"""Merging the ``results.json`` of earlier ego evaluations (``evaluate_ego.py --combine``).

Each file holds summary rows (planner, traffic), per-run rows (one trained run each) and
paired counts. Files are merged when their episodes are disjoint, e.g. PPO runs evaluated
in separate processes: a (planner, traffic) row found in several files is pooled, rates
exactly (the Wilson interval of the summed counts), means as the episode-weighted mean
without an interval (the episodes are not in the files). What would count episodes twice
is refused with a :class:`~policies.rl.runs.RunError`: a file named twice, one run's rows
in two files, and the rows of a planner without runs (a baseline, which every evaluation
drives on the same seeds) in two files.
"""

from __future__ import annotations

import json
from pathlib import Path

from policies.rl.runs import RunError
from policies.statistics import wilson_interval

RATES = ("ego_collision_rate", "ego_offroad_rate", "ego_failure_rate")


def load_results(paths: str) -> tuple[dict, dict, list, bool | None]:
    """Summaries, per-run summaries, paired counts and the PPO egos' ``mask_actions`` (None:
    not recorded) of the comma-separated ``results.json`` files ``paths``, merged (module
    docstring); a RunError naming ``--combine`` for files that cannot be merged, or whose
    PPO egos chose their maneuvers differently (with and without the action mask)."""
    summaries, per_run, paired, masks = {}, {}, [], {}
    files: dict[Path, dict] = {}
    found_in: dict[tuple[str, str], list[Path]] = {}  # summary row -> the files holding it
    for path in [Path(p) for p in paths.split(",") if p]:
        if path.resolve() in files:
            raise RunError(f"--combine names {path} twice: its episodes would count twice")
        content = files[path.resolve()] = read_results(path)
        masks[path] = content.get("mask_actions")  # None: no PPO rows, or written before it
        paired.extend(content.get("paired", []))
        for target, rows in ((summaries, content["summary"]), (per_run, content["per_run"])):
            for row in rows:
                row = dict(row)
                key = row.pop("planner"), row.pop("traffic")
                if target is per_run and key in per_run:
                    raise RunError(f"--combine: the rows of {key[0]} under {key[1]} are in two "
                                   "files: one run's episodes would count twice")  # fmt: skip
                if target is summaries:
                    found_in.setdefault(key, []).append(path)
                target[key] = pool(target[key], row) if key in target else row
    settings = {mask for mask in masks.values() if mask is not None}
    if len(settings) > 1:
        raise RunError(
            "--combine: the files' PPO egos were evaluated with and without the action mask "
            f"(mask_actions: {', '.join(f'{path}: {mask}' for path, mask in masks.items())})"
        )
    trained = {planner.split(" (seed ")[0] for planner, _ in per_run}
    for (planner, traffic), holders in found_in.items():
        if len(holders) > 1 and planner.removesuffix("-initial") not in trained:
            raise RunError(
                f"--combine: {planner} under {traffic} is in {holders[0]} and {holders[1]}: "
                "a baseline drives the same episodes in every evaluation; evaluate it in one "
                "of them (--no-baselines in the others)"
            )
    return summaries, per_run, paired, settings.pop() if settings else None


def read_results(path: Path) -> dict:
    """An earlier ``results.json``, or a RunError naming ``--combine`` and the file."""
    if not path.is_file():
        raise RunError(f"--combine {path}: no such file (an evaluate_ego.py results.json)")
    try:
        content = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise RunError(f"--combine {path}: not valid JSON ({error})") from None
    if not isinstance(content, dict) or not {"summary", "per_run"} <= set(content):
        raise RunError(f"--combine {path}: not an evaluate_ego.py results.json")
    return content


def pool(first: dict, second: dict) -> dict:
    """Two summaries of disjoint episodes of one (planner, traffic) row as one."""
    pooled = {}
    for metric, a in first.items():
        b = second[metric]
        count = a["n"] + b["n"]
        weighted = [e["value"] * e["n"] for e in (a, b) if e["value"] is not None and e["n"]]
        value = (
            sum(weighted) / sum(e["n"] for e in (a, b) if e["value"] is not None)
            if weighted
            else None
        )
        if metric in RATES:
            hits = round(a["value"] * a["n"] + b["value"] * b["n"])
            low, high = wilson_interval(hits, count)
            pooled[metric] = {"value": hits / count, "low": low, "high": high, "n": count}
        else:
            pooled[metric] = {"value": value, "low": None, "high": None, "n": count}
    return pooled


__all__ = ["RATES", "load_results", "pool", "read_results"]
