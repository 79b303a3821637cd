"""Realism of learned traffic in closed loop, against IDM traffic and log replay.

One run measures, on the same scenes and seeds, the unguided generator as it ships
(``riskflow-eval`` method ``bits`` with no options: the realistic base, avoidance steps,
holding at rest, blending first), IDM traffic (``idm``) and log replay (``replay``), all
against the IDM ego, closed loop, ``--duration`` seconds. ``--raw`` adds ``bits-raw``
(the raw generator, without that rule layer) next to ``bits``; ``--checkpoint`` gives
the generator rows other weights (a row of each generator method per file, named by it).
The rollouts are ``riskflow-eval``'s (:func:`policies.evaluation.rollout.rollout_episode`);
the numbers are :mod:`riskflow_env.metrics`'s. Columns (the controlled vehicles are the
non-ego ones):

* ``veh_coll``: share of non-ego vehicles that overlap another non-ego vehicle at some
  step (:func:`~riskflow_env.metrics.collision_involvement`); ``log_veh_coll``: the same
  share in the log itself, its boxes at the same slots and steps (recorded boxes can
  overlap: the floor of a model that keeps them where the log has them);
* ``scr_nonego``: share of rollouts with a non-ego pair overlap; ``ego_coll``: share of
  rollouts where the ego is hit;
* ``orr`` / ``orr_fp``: off-road share of agent-steps by centroid / by footprint;
* ``jerk_p95`` / ``lat_p95``: p95 of |longitudinal jerk| [m/s^3] and |lateral
  acceleration| [m/s^2] (KDD's samples of the simulated tracks);
* ``jerk_replan_p95`` / ``jerk_within_p95``: p95 |jerk| at the steps that switch to a new
  plan (step index 0 mod the planning interval) and at the other steps
  (:func:`~riskflow_env.metrics.jerk_steps`; the first simulated step, which follows
  the log, is in neither); the JSON has every phase (``jerk_p95_by_phase``);
* ``still_kept``: of the vehicles that stand still in the log (logged positions within
  0.5 m), the share the simulation keeps within 2 m of their log
  (:func:`~riskflow_env.metrics.standstill_drift`; NaN without such vehicles);
* the counter-metrics of safety (:func:`~riskflow_env.metrics.progress`):
  ``progress_median`` (per vehicle that moves in the log, the path driven over the path
  logged), ``stalled`` (the share of those below half of it), ``turned`` (of the
  vehicles parked in the log, the share turned over 20 degrees in place) and
  ``edge_hard`` (of the vehicle-steps heading for the map's border, the share braking
  or turning over 3 m/s^2; ``log_edge_hard``: the log's on the same slots);
* ``wosac`` (mean per-rollout metametric), ``kdd``, ``ade`` / ``fde`` [m], ``wall_s``
  (rollouts and metrics, summed over this row's rollouts).

By default 14 scenes, two per road family of the shipped evaluation bank (``--full``:
every scene)::

    python benchmarks/traffic_realism.py [--raw] [--checkpoint A.pt B.pt]
        [--scenes 14 | --full] [--seeds 0 1 2] [--bank DIR] [--workers 1]
        [--out realism.json] [--leave-when-log-ends]
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from methods import with_raw

from policies.cli_inputs import check_seeds
from policies.dataclass_cli import parse_dataclass
from policies.evaluation.options import SHIPPED, EvalOptions, Job, RunConfig
from policies.evaluation.rollout import rollout_episode
from policies.registry import method_spec
from riskflow_env.cli_errors import run_script
from riskflow_env.config import DynamicsConfig
from riskflow_env.metrics import (
    KinematicSamples,
    collision_involvement,
    collisions,
    jerk_steps,
    kinematic_samples,
    method_metrics,
    progress,
    rollout_metrics,
    standstill_drift,
    wosac_scene,
)
from riskflow_env.scenarios import Scenario, shipped_bank
from riskflow_env.scenarios.folders import open_scenes

GENERATOR = "bits"  # the unguided generator as it ships
BASELINES = ("idm", "replay")
STILL_RADIUS = 2.0  # [m] a vehicle that stands still in the log may drift this far
COLUMNS = (  # (key, header, format)
    ("veh_coll", "veh. in coll.", "{:.3f}"),
    ("log_veh_coll", "log veh. in coll.", "{:.3f}"),
    ("scr_nonego", "SCR non-ego", "{:.2f}"),
    ("ego_coll", "ego coll.", "{:.2f}"),
    ("orr", "ORR centroid", "{:.4f}"),
    ("orr_fp", "ORR footprint", "{:.4f}"),
    ("jerk_p95", "p95 jerk", "{:.2f}"),
    ("lat_p95", "p95 lat. acc.", "{:.2f}"),
    ("jerk_replan_p95", "p95 jerk re-plan", "{:.2f}"),
    ("jerk_within_p95", "p95 jerk within", "{:.2f}"),
    ("still_kept", "still within 2 m", "{:.3f}"),
    ("progress_median", "progress (median)", "{:.2f}"),
    ("stalled", "stalled", "{:.3f}"),
    ("turned", "parked turned", "{:.3f}"),
    ("edge_hard", "hard at edge", "{:.3f}"),
    ("log_edge_hard", "log hard at edge", "{:.3f}"),
    ("wosac", "WOSAC", "{:.3f}"),
    ("kdd", "KDD", "{:.3f}"),
    ("ade", "ADE", "{:.2f}"),
    ("fde", "FDE", "{:.2f}"),
    ("wall_s", "wall [s]", "{:.0f}"),
)


@dataclass(frozen=True)
class Options:
    """Benchmark options."""

    raw: bool = False
    """also bits-raw (the raw generator, without the rule layer) next to bits"""
    checkpoint: tuple[str, ...] = ()
    """generator checkpoints, a row of each generator method per file (named by it);
    default: the shipped one"""
    baselines: tuple[str, ...] = BASELINES
    """reference methods of riskflow-eval measured in the same run"""
    bank: str | None = None
    """scene folder (a bank of .npz scenes or a ScenarioNet dataset); default: the
    shipped evaluation bank"""
    scenes: int = 14
    """number of scenes, spread evenly over the road families"""
    full: bool = False
    """every scene of the bank"""
    seeds: tuple[int, ...] = (0,)
    """rollout seeds"""
    duration: float = 10.0
    """[s] episode length"""
    interval: float = 0.5
    """[s] planning interval of the generator"""
    ego: str = "idm"
    """ego planner (riskflow-eval --ego)"""
    leave_when_log_ends: bool = False
    """vehicles leave the scene when their logged track ends (riskflow-eval
    --leave-when-log-ends), for every row alike"""
    device: str = "cpu"
    """torch device of the generator"""
    workers: int = 1
    """worker processes (spawned, one torch thread each)"""
    out: str | None = None
    """write the rows as JSON to this file"""

    def __post_init__(self) -> None:
        if self.scenes < 1 or self.workers < 1:
            raise ValueError(
                f"--scenes and --workers must be >= 1, got {self.scenes} and {self.workers}"
            )
        if not self.duration > 0 or not self.interval > 0:
            raise ValueError(
                f"--duration and --interval must be > 0, got {self.duration} and {self.interval}"
            )
        object.__setattr__(self, "seeds", check_seeds(self.seeds))
        for path in self.checkpoint:
            if not Path(path).is_file():
                raise ValueError(f"--checkpoint: no file {path}")


PROG = "traffic_realism.py"  # the name in usage and error lines


def parse_args(argv: Sequence[str] | None = None) -> Options:
    return parse_dataclass(
        Options, argv, prog=PROG, description=__doc__.split("\n\n")[0], debug=True
    )


def pick_scenes(scenes: Sequence[Scenario], count: int) -> list[int]:
    """Indices of ``count`` scenes taken round-robin over the families (in bank order),
    so every family appears once ``count`` >= the number of families."""
    families: dict[str, list[int]] = {}
    for index, scene in enumerate(scenes):
        families.setdefault(scene.family, []).append(index)
    queues = list(families.values())
    picked: list[int] = []
    for rank in range(max(len(q) for q in queues)):
        picked += [q[rank] for q in queues if rank < len(q)]
    return sorted(picked[:count])


@dataclass(frozen=True)
class RealismJob:
    """One rollout of the benchmark: the evaluation job, its row label and the
    planning period [steps] (for jerk per step of the re-plan cycle)."""

    job: Job
    label: str
    period: int


def measure(item: RealismJob) -> dict[str, Any]:
    """One rollout and its per-rollout numbers and samples."""
    start = time.perf_counter()
    _, record, _ = rollout_episode(item.job)
    hit = collisions(record)
    involved = collision_involvement(hit.pairs, record.ego_index) & record.evaluated
    logged = dataclasses.replace(record, states=record.reference, valid=record.reference_valid)
    log_hit = collisions(logged).pairs
    log_involved = collision_involvement(log_hit, record.ego_index) & record.evaluated
    jerk, step = jerk_steps(record)
    still, drift = standstill_drift(record)
    moving = progress(record)
    return {
        "label": item.label,
        "metrics": rollout_metrics(record),
        "vehicles": int(record.evaluated.sum()),
        "involved": int(involved.sum()),
        "log_involved": int(log_involved.sum()),
        "nonego_collision": bool(involved.any()),
        "still": int(still.sum()),
        "still_kept": int((drift[still] <= STILL_RADIUS).sum()),
        "progress": moving.ratio[moving.mover],
        "samples": kinematic_samples(record),
        "jerk": jerk,
        "step": step,
        "period": item.period,
        "wosac": float(wosac_scene([record])["metametric"]),
        "wall_s": time.perf_counter() - start,
    }


def _p95(values: np.ndarray) -> float:
    return float(np.percentile(np.abs(values), 95)) if values.size else float("nan")


def summarise(label: str, results: list[dict[str, Any]]) -> dict[str, Any]:
    """One table row from the rollouts of one method."""
    samples = [r["samples"] for r in results]
    pooled = KinematicSamples.concatenate(samples).generated
    agg = method_metrics([r["metrics"] for r in results], samples)
    jerk = np.concatenate([r["jerk"] for r in results])
    step = np.concatenate([r["step"] for r in results])
    period = results[0]["period"]
    phase = np.where(step > 0, step % period, -1)  # step 0 follows the log: no re-plan
    vehicles = sum(r["vehicles"] for r in results)

    def share(key: str) -> float:  # of the non-ego vehicles
        return sum(r[key] for r in results) / vehicles if vehicles else float("nan")

    still, nan = sum(r["still"] for r in results), float("nan")
    ratios = np.concatenate([r["progress"] for r in results])
    return {
        "label": label,
        "rollouts": len(results),
        "vehicles": vehicles,
        "veh_coll": share("involved"),
        "log_veh_coll": share("log_involved"),
        "scr_nonego": float(np.mean([r["nonego_collision"] for r in results])),
        "ego_coll": agg["ego_collision_rate"],
        "scr": agg["scr"],
        "orr": agg["orr"],
        "orr_fp": agg["orr_footprint"],
        "still_kept": sum(r["still_kept"] for r in results) / still if still else nan,
        "progress_median": float(np.median(ratios)) if ratios.size else nan,
        "stalled": agg["stalled_share"],
        "turned": agg["turned_share"],
        "edge_hard": agg["edge_hard_share"],
        "log_edge_hard": agg["log_edge_hard_share"],
        "jerk_p95": _p95(pooled["jerk"]),
        "lat_p95": _p95(pooled["lateral_acceleration"]),
        "jerk_replan_p95": _p95(jerk[phase == 0]),
        "jerk_within_p95": _p95(jerk[phase > 0]),
        "jerk_p95_by_phase": [_p95(jerk[phase == p]) for p in range(period)],
        "wosac": float(np.mean([r["wosac"] for r in results])),
        "kdd": agg["kdd"],
        "ade": agg["ade"],
        "fde": agg["fde"],
        "wall_s": float(sum(r["wall_s"] for r in results)),
    }


def _jobs(args: Options, scenes: Sequence[Scenario], picked: list[int]) -> list[RealismJob]:
    options = EvalOptions(
        data=args.bank,
        ego=args.ego,
        duration=args.duration,
        device=args.device,
        leave_when_log_ends=args.leave_when_log_ends,
    )
    run = RunConfig.from_options(options)
    period = round(args.interval / DynamicsConfig().dt)  # steps per planning cycle
    methods = [(name, {}, name) for name in with_raw((GENERATOR,), args.raw)]
    if args.checkpoint:
        names = [Path(p).name for p in args.checkpoint]
        labels = names if len(set(names)) == len(names) else list(args.checkpoint)
        methods = [
            (name, {"checkpoint": str(Path(path).resolve())}, f"{name} {label}")
            for path, label in zip(args.checkpoint, labels, strict=True)
            for name, _, _ in methods
        ]
    methods += [(name, {}, name) for name in args.baselines]
    jobs = []
    for method, options, label in methods:
        interval = args.interval if method_spec(method).uses_interval else None
        for index in picked:
            for seed in args.seeds:
                job = Job(method, options, None, interval, scenes[index].name, index, seed, run)
                jobs.append(RealismJob(job, label, period))
    return jobs


def _results(jobs: list[RealismJob], workers: int):
    if workers <= 1:
        yield from map(measure, jobs)
        return
    from policies.evaluation.runner import _init_worker

    with multiprocessing.get_context("spawn").Pool(workers, initializer=_init_worker) as pool:
        yield from pool.imap(measure, jobs, chunksize=1)


def markdown(rows: Sequence[dict[str, Any]]) -> str:
    """The rows as a Markdown table (NaN as 'n/a')."""

    def cell(value: Any, fmt: str) -> str:
        return "n/a" if value is None or not np.isfinite(value) else fmt.format(value)

    lines = ["| generator | " + " | ".join(h for _, h, _ in COLUMNS) + " |",
             "|---|" + "---:|" * len(COLUMNS)]  # fmt: skip
    for row in rows:
        lines.append(f"| {row['label']} | "
                     + " | ".join(cell(row[k], f) for k, _, f in COLUMNS) + " |")  # fmt: skip
    return "\n".join(lines)


def _write(path: str, payload: dict[str, Any]) -> None:
    def clean(value: Any) -> Any:
        if isinstance(value, float) and not np.isfinite(value):
            return None
        if isinstance(value, list):
            return [clean(v) for v in value]
        return value

    payload = {**payload, "rows": [{k: clean(v) for k, v in r.items()} for r in payload["rows"]]}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as handle:
        json.dump(payload, handle, indent=1)
        handle.flush()
        os.fsync(handle.fileno())


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """Run the benchmark, print the table; returns the rows."""
    args = parse_args(argv)
    start = time.perf_counter()
    bank = shipped_bank("eval") if args.bank is None else open_scenes(args.bank)
    scenes = [bank[i] for i in range(len(bank))]
    picked = list(range(len(scenes))) if args.full else pick_scenes(scenes, args.scenes)
    if args.bank is None:
        args = dataclasses.replace(args, bank=SHIPPED)
    jobs = _jobs(args, scenes, picked)
    dt = DynamicsConfig().dt
    config = {
        "bank": args.bank,
        "scenes": [scenes[i].name for i in picked],
        "seeds": list(args.seeds),
        "duration_s": args.duration,
        "interval_s": args.interval,
        "dt": dt,
        "ego": args.ego,
        "methods": list(dict.fromkeys(job.job.method for job in jobs)),
        "checkpoints": list(args.checkpoint) or ["shipped"],
    }
    print(f"{len(picked)} scenes ({len({scenes[i].family for i in picked})} families) x "
          f"{len(args.seeds)} seeds x {len(jobs) // max(len(picked) * len(args.seeds), 1)} "
          f"methods, {args.duration:g} s closed loop, {args.ego} ego", file=sys.stderr)  # fmt: skip
    per_label: dict[str, list[dict[str, Any]]] = {}
    for job in jobs:
        per_label.setdefault(job.label, [])
    rows: list[dict[str, Any]] = []
    expected = {label: sum(j.label == label for j in jobs) for label in per_label}
    for done, result in enumerate(_results(jobs, args.workers), 1):
        label = result["label"]
        per_label[label].append(result)
        print(f"  {done}/{len(jobs)} {label} ({result['wall_s']:.1f} s)", file=sys.stderr)
        if len(per_label[label]) == expected[label]:
            rows.append(summarise(label, per_label[label]))
            if args.out:
                _write(args.out, {"config": config, "rows": rows})
    wall = time.perf_counter() - start
    print(markdown(rows))
    print(f"\ntotal wall time {wall:.0f} s", file=sys.stderr)
    if args.out:
        _write(args.out, {"config": config, "rows": rows, "total_wall_s": wall})
    return rows


if __name__ == "__main__":
    run_script(PROG, main)
