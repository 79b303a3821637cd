"""Merging the ``results.json`` of earlier ego evaluations (``evaluate_ego.py --combine``).

Each file holds summary rows (planner, traffic), per-run rows (one trained run each),
paired counts and the episodes it drove (``episodes``: the scene names, and the seeds of
every per-run and baseline row). Files are merged when their episodes are disjoint, e.g.
PPO runs evaluated in separate processes, or one baseline on other seeds: a (planner,
traffic) row found in several files is pooled, rates exactly (the Wilson interval of the
summed counts), means as the episode-weighted mean without an interval (the episodes are
not in the files). What would count episodes twice is refused with a
:class:`~policies.rl.runs.RunError`: a file named twice, and a row whose scenes and seeds
overlap those of the same row in another file (files written before ``episodes`` was
recorded are pooled as they are).
"""

from __future__ import annotations

import json
from pathlib import Path

from policies.rl.runs import RunError
from policies.statistics import wilson_interval

RATES = ("ego_collision_rate", "ego_offroad_rate", "ego_failure_rate")


def load_results(paths: str) -> tuple[dict, dict, list, bool | None, dict | None]:
    """Summaries, per-run summaries, paired counts, the PPO egos' ``mask_actions`` (None:
    not recorded) and the episodes (None: a file did not record them) of the
    comma-separated ``results.json`` files ``paths``, merged (module docstring); a RunError
    naming ``--combine`` for files that cannot be merged, or whose PPO egos chose their
    maneuvers differently (with and without the action mask)."""
    summaries, per_run, paired, masks = {}, {}, [], {}
    files: dict[Path, dict] = {}
    for path in [Path(p) for p in paths.split(",") if p]:
        if path.resolve() in files:
            raise RunError(f"--combine names {path} twice: its episodes would count twice")
        content = read_results(path)
        for other, earlier in files.items():
            _check_disjoint(path, content.get("episodes"), other, earlier.get("episodes"))
        files[path.resolve()] = content
        masks[path] = content.get("mask_actions")  # None: no PPO rows, or written before it
        paired.extend(content.get("paired", []))
        for target, rows in ((summaries, content["summary"]), (per_run, content["per_run"])):
            for row in rows:
                row = dict(row)
                key = row.pop("planner"), row.pop("traffic")
                target[key] = pool(target[key], row) if key in target else row
    settings = {mask for mask in masks.values() if mask is not None}
    if len(settings) > 1:
        raise RunError(
            "--combine: the files' PPO egos were evaluated with and without the action mask "
            f"(mask_actions: {', '.join(f'{path}: {mask}' for path, mask in masks.items())})"
        )
    recorded = [content.get("episodes") for content in files.values()]
    episodes = None
    if all(recorded):
        seeds: dict[str, list[int]] = {}
        for record in recorded:
            for planner, row_seeds in record["seeds"].items():
                seeds.setdefault(planner, []).extend(row_seeds)
        names = dict.fromkeys(name for record in recorded for name in record["scenes"])
        episodes = {"scenes": list(names), "seeds": seeds}
    return summaries, per_run, paired, settings.pop() if settings else None, episodes


def _check_disjoint(path: Path, episodes: dict | None, other: Path, known: dict | None) -> None:
    """RunError when a row of ``path`` drove episodes (a scene and a seed) that the same
    row of ``other`` drove; nothing to check where either file did not record them."""
    if not (episodes and known) or not set(episodes["scenes"]) & set(known["scenes"]):
        return
    for planner, seeds in episodes["seeds"].items():
        shared = sorted(set(seeds) & set(known["seeds"].get(planner, ())))
        if shared:
            raise RunError(
                f"--combine: {planner} drove the same episodes in {other} and {path} (seeds "
                f"{shared} on the same scenes): they would count twice"
            )


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
