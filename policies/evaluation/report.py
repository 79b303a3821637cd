"""``report.md`` from a results folder: metric and timing tables per (K, planning interval).

One table per (K, interval) found in the rows. A method without K (idm, replay, bits...)
joins every table, one without a planning interval every interval. Within a table the
methods are compared on the scenes (and seeds) that all of them have finished, so an
interrupted run never compares methods over different scenes; the table says how many.
Aggregation is :func:`riskflow_env.metrics.method_metrics` (SCR and ego rate over
rollouts, ORR over pooled agent-steps, ADE/FDE over pooled agents, KDD over pooled
samples), the mean of the per-rollout WOSAC scores, the mean time of the first collision
(any, and the ego's) over the rollouts that have one, the share of rollouts with an ego
collision the ego could have avoided ("ego avoidable", :mod:`policies.stress.failures`:
the stress test's headline, next to the ego SCR that counts every ego collision), and
CS / RS
(:func:`riskflow_env.metrics.safety_realism_scores`) across the table's scenario
generators: reference traffic (IDM, replay, constant velocity: ``MethodSpec.reference``)
is shown but left out of the normalisation. CS normalises SCR, or the ego-collision rate
when the run's guidance target is the ego (the attack's own success).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from policies.evaluation.results import ResultsStore
from policies.evaluation.rollout import HISTORY
from policies.evaluation.table import Table
from policies.registry import METHODS
from riskflow_env.atomic_files import write_text
from riskflow_env.config import DynamicsConfig
from riskflow_env.metrics import ROLLOUT_KEYS, method_metrics, safety_realism_scores

REFERENCE_METHOD = "riskflow"  # timing ratios are to this label when present
METRIC_COLUMNS = (
    ("scr", "SCR"),
    ("ego_collision_rate", "ego SCR"),
    ("avoidable_failure_rate", "ego avoidable"),
    ("first_collision_s", "TTFC [s]"),
    ("first_ego_collision_s", "ego TTFC [s]"),
    ("orr", "ORR"),
    ("orr_footprint", "ORR fp"),
    ("ade", "ADE [m]"),
    ("fde", "FDE [m]"),
    ("kdd", "KDD"),
    ("wosac", "WOSAC"),
    ("progress", "progress"),
    ("stalled_share", "stalled"),
    ("turned_share", "parked turned"),
    ("edge_hard_share", "hard at edge"),
    ("cs", "CS"),
    ("rs", "RS"),
)


_SAFETY_NAMES = {
    "scr": "SCR",
    "ego_collision_rate": "the ego-collision rate (the guidance target is the ego)",
}


def _nan(value: Any) -> float:
    return float("nan") if value is None else float(value)


def _k_order(k: int | str | None) -> tuple[int, float]:
    return (0, -1) if k is None else (1, math.inf) if k == "all" else (1, float(k))


def table_keys(rows: list[dict]) -> list[tuple[int | str | None, float | None]]:
    """The (K, interval) pairs of the tables, sorted: those of the rows with a K, else
    the intervals of the rows with one, else a single table."""
    keys = {(row["k"], row["interval"]) for row in rows if row["k"] is not None}
    keys = keys or {(None, row["interval"]) for row in rows if row["interval"] is not None}
    return sorted(keys or {(None, None)}, key=lambda key: (_k_order(key[0]), key[1] or 0.0))


def safety_metric(target: str | None) -> str:
    """The metric CS normalises: the ego-collision rate when the guidance target is the
    ego, else SCR (the paper's)."""
    return "ego_collision_rate" if target == "ego" else "scr"


def build_tables(store: ResultsStore) -> list[Table]:
    """Every table of the results folder."""
    rows = store.rows()
    safety = safety_metric(store.config().get("target"))
    tables = []
    for k, interval in table_keys(rows):
        members = [
            row for row in rows
            if row["k"] in (None, k) and row["interval"] in (None, interval)
        ]  # fmt: skip
        by_label: dict[str, list[dict]] = {}
        for row in members:
            by_label.setdefault(row["label"], []).append(row)
        common = set.intersection(
            *({(r["scene"], r["seed"]) for r in v} for v in by_label.values())
        )
        metrics, timing = {}, {}
        left_out = {
            label: len(group) - sum((r["scene"], r["seed"]) in common for r in group)
            for label, group in sorted(by_label.items())
        }
        for label, group in sorted(by_label.items()):
            group = sorted((r for r in group if (r["scene"], r["seed"]) in common),
                           key=lambda r: (r["scene_index"], r["seed"]))  # fmt: skip
            metrics[label] = _method_metrics(store, group)
            timing[label] = _timing(group)
        references = frozenset(
            label for label, group in by_label.items()
            if group[0]["method"] in METHODS and METHODS[group[0]["method"]].reference
        )  # fmt: skip
        for label in metrics:
            metrics[label].update(cs=math.nan, rs=math.nan)
        generators = {label: m for label, m in metrics.items() if label not in references}
        for label, scores in safety_realism_scores(generators, safety).items():
            metrics[label].update(scores)
        _add_ratios(timing, _reference_label(by_label))
        left_out = {label: n for label, n in left_out.items() if n}
        tables.append(
            Table(k, interval, len(common), metrics, timing, references, safety, left_out)
        )
    return tables


def _method_metrics(store: ResultsStore, rows: list[dict]) -> dict[str, float]:
    numeric = [{key: _nan(row.get(key)) for key in ROLLOUT_KEYS} for row in rows]
    out = method_metrics(numeric, [store.samples(row) for row in rows])
    scores = [row["wosac"]["metametric"] for row in rows if row.get("wosac")]
    out["wosac"] = float(np.mean([_nan(s) for s in scores])) if scores else float("nan")
    for key, name in (("first_collision_s", "first_collision_step"),
                      ("first_ego_collision_s", "first_ego_collision_step")):  # fmt: skip
        out[key] = _mean_first_time([_nan(row.get(name)) for row in rows])
    out["avoidable_failure_rate"] = _avoidable_rate(rows)
    return out


def _avoidable_rate(rows: list[dict]) -> float:
    """Share of rollouts with an ego collision the ego could have avoided (shown by the
    escape search, :mod:`policies.stress.failures`); NaN where a row predates it."""
    if not rows or any("failures" not in row for row in rows):
        return math.nan
    return float(np.mean([any(f["avoidable"] for f in row["failures"]) for row in rows]))


def _mean_first_time(steps: list[float]) -> float:
    """Mean time [s] after the start of the first collision over the rollouts with one,
    from the record's step indices (``HISTORY`` logged steps and the start state are
    context, -1: none; NaN where a row predates the key)."""
    if not steps or any(math.isnan(step) for step in steps):
        return math.nan
    times = [(step - HISTORY) * DynamicsConfig().dt for step in steps if step >= 0]
    return float(np.mean(times)) if times else math.nan


def _timing(rows: list[dict]) -> dict[str, float]:
    timing = [row["timing"] for row in rows]
    cycles = sum(t["planning_cycles"] for t in timing)
    planning = sum(t["planning_s"] for t in timing)
    return {
        "rollouts": float(len(rows)),
        "total_s": sum(t["rollout_s"] for t in timing),
        "per_scene_s": float(np.mean([t["rollout_s"] for t in timing])) if timing else math.nan,
        "cycles_per_rollout": cycles / len(rows) if rows else math.nan,
        "cycle_ms": 1e3 * planning / cycles if cycles else math.nan,
        "cycle_ms_max": max((_nan(t["cycle_ms_max"]) for t in timing), default=math.nan),
    }


def _reference_label(by_label: dict[str, list[dict]]) -> str | None:
    """The label timings are compared to: plain riskflow, else riskflow with options."""
    if REFERENCE_METHOD in by_label:
        return REFERENCE_METHOD
    return next((lab for lab, rows in sorted(by_label.items())
                 if rows[0]["method"] == REFERENCE_METHOD), None)  # fmt: skip


def _add_ratios(timing: dict[str, dict[str, float]], reference_label: str | None) -> None:
    reference = timing.get(reference_label) if reference_label else None
    for values in timing.values():
        for name in ("total_s", "cycle_ms"):
            base = reference[name] if reference else math.nan
            values[f"{name}_ratio"] = values[name] / base if base and base > 0 else math.nan


def _cell(value: float, digits: int = 3) -> str:
    return "n/a" if value is None or math.isnan(value) else f"{value:.{digits}f}"


def metrics_markdown(table: Table) -> str:
    """The metric table: raw metrics next to CS and RS."""
    lines = [
        "| method | rollouts | " + " | ".join(name for _, name in METRIC_COLUMNS) + " |",
        "|---|---:|" + "---:|" * len(METRIC_COLUMNS),
    ]
    for label, values in table.metrics.items():
        cells = [
            "ref." if label in table.references and key in ("cs", "rs")
            else _cell(values.get(key, math.nan), 2 if key.endswith("_s") else 3)
            for key, _ in METRIC_COLUMNS
        ]  # fmt: skip
        count = int(values["num_rollouts"])
        lines.append(f"| {label} | {count} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def timing_markdown(table: Table) -> str:
    """The timing table: total, per scene, per planning cycle, ratios to riskflow."""
    lines = [
        "| method | total [s] | per scene [s] | cycles / scene | per cycle [ms] | "
        f"max cycle [ms] | total / {REFERENCE_METHOD} | cycle / {REFERENCE_METHOD} |",
        "|---|" + "---:|" * 7,
    ]
    for label, t in table.timing.items():
        cells = [
            _cell(t["total_s"], 1), _cell(t["per_scene_s"], 2), _cell(t["cycles_per_rollout"], 1),
            _cell(t["cycle_ms"], 1), _cell(t["cycle_ms_max"], 1),
            _cell(t["total_s_ratio"], 2), _cell(t["cycle_ms_ratio"], 2),
        ]  # fmt: skip
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_report(out: str | Path, plots: bool = True) -> Path:
    """Write ``report.md`` (and the PNG plots) into the results folder ``out``."""
    if Path(out).exists() and not Path(out).is_dir():
        raise NotADirectoryError(f"--out {out} is a file, not a results folder")
    if not Path(out).exists():
        raise FileNotFoundError(f"--out {out}: no such folder (riskflow-eval --out writes one)")
    store = ResultsStore(out)
    rows = store.rows()
    if not rows:
        raise FileNotFoundError(f"--out {out}: no results ({store.results} is missing or empty)")
    tables = build_tables(store)
    config = store.config()
    duration = config.get("duration", "?")
    lines = [
        "# riskflow-eval report",
        "",
        f"{len(rows)} rollouts in `{store.results.name}`. Run settings: "
        + ", ".join(f"{k}={v}" for k, v in sorted(config.items()) if k != "checkpoints")
        + "".join(
            f"; checkpoint {path} (weights_sha256 {digest[:12]})"
            for path, digest in sorted(config.get("checkpoints", {}).items())
        )
        + ".",
        "",
        "SCR and ego SCR: shares of rollouts with a collision (any pair / the ego's). ORR: "
        "share of agent-steps off the road (centre; fp: footprint). ADE/FDE [m] and KDD "
        "(mean W1 of longitudinal / lateral acceleration and jerk) against the log, for "
        "the non-ego vehicles. WOSAC: mean per-rollout metametric (one rollout per scene "
        "and seed). TTFC: mean time [s] of the first collision (any / the ego's) over "
        "the rollouts that have one. CS, RS: min-max normalised across the scenario "
        "generators of each table (docs/reference/metrics.md; 'ref.': reference traffic, outside "
        f"the normalisation); CS normalises {_SAFETY_NAMES[tables[0].safety_metric]}. "
        "Compare them only within a table.",
    ]  # fmt: skip
    for table in tables:
        timing = f"Timing (rollouts of {duration} s; a cycle is one call that planned):"
        rollouts = f"{table.scenes} rollout{'' if table.scenes == 1 else 's'}"
        lines += ["", f"## {table.title} ({rollouts} a method: scene x seed pairs)", ""]
        if table.left_out:
            counts = ", ".join(f"{label} {n}" for label, n in table.left_out.items())
            lines += [
                "Only the scenes and seeds every method ran are compared; rollouts left out "
                f"(in results.jsonl still): {counts}.",
                "",
            ]
        lines += [metrics_markdown(table), "", timing, "", timing_markdown(table)]
    if plots:
        from policies.evaluation.plots import write_plots  # matplotlib only when plotting

        files = write_plots(tables, store.out)
        lines += ["", "## Plots", ""] + [f"![{f.stem}]({f.name})" for f in files]
    path = store.out / "report.md"
    write_text(path, "\n".join(lines) + "\n")
    return path
