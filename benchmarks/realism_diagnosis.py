"""Where the unguided generator's collisions and off-road steps come from.

    python benchmarks/realism_diagnosis.py                      # first 21 eval scenes
    python benchmarks/realism_diagnosis.py --raw                # and the raw generator
    python benchmarks/realism_diagnosis.py --scenes 105 --checkpoint runs/x/generator.pt
    python benchmarks/realism_diagnosis.py --bank DIR --scenes 4   # e.g. real scenes as .npz

For each scene of the shipped evaluation bank (scenes 0..N-1: the families take turns;
``--bank``: a scene folder of your own), the unguided generator as it ships
(``riskflow-eval`` method ``bits`` with no options: the realistic base, re-planning every
0.5 s) drives every vehicle but an IDM ego for 10 s; ``--raw`` runs ``bits-raw`` (the raw
generator: no avoidance steps, no holding at rest) on the same scenes too, each method's
tables under its name. Episodes run their full length (nothing terminates on a
collision or off the road) so that every time bucket sees every scene. Printed, as
Markdown tables:

* **open loop vs closed loop, by road family:** the first planning cycle's one-shot plans
  (5.2 s, rolled out, no re-planning) - do they already overlap another vehicle's plan or
  leave the road? - against the closed loop (re-planning on its own outputs);
* **collisions by kind:** non-ego pairs vs ego-involved; rear-end (front meets rear),
  head-on (front meets front) or side (the event log's contact kinds); with a standing
  vehicle (either below 0.5 m/s at contact) or between moving ones;
* **off-road by time bucket** (2 s buckets): drift appears as a share rising with time;
* **off-road past a road's end:** of the off-road agent-steps (by centroid), those of
  vehicles that drove on past the end of a lane without successor, along it: roads that
  the map cuts (the exits of the U-turn, merge and intersection maps), where the recorded
  vehicles leave the scene and a closed-loop vehicle runs onto the map's border;
* **vehicles at rest at the start** (speed <= ``REST_SPEED``): how far the first cycle's
  plan moves each (its largest distance from the start over the plan), for those that
  stand in the log over the same steps (within 0.5 m) and those that start (beyond 2 m),
  and the share that the holding rule at 0.5, 1 and 2 m would hold (``hold_distance``,
  :mod:`policies.learned.plan_stitching`; ``bits`` holds at its default, ``bits-raw``
  not at all);
* **lateral acceleration by road family:** p95 |v x yaw rate| of the generator's
  vehicles against their own logs over the same steps (KDD's samples,
  :func:`riskflow_env.metrics.kinematic_samples`): whether a high pooled value is the
  generator's or the roads' (the recorded traffic drives the racetrack and the U-turn
  faster than real drivers would).

Curved roads are the roundabout, racetrack, U-turn and intersection families.
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass

import numpy as np
from methods import make_policy, with_raw

from policies.cli_inputs import check_seeds
from policies.dataclass_cli import parse_dataclass
from policies.evaluation.rollout import rollout_record
from policies.harness import ClosedLoop
from policies.learned.plan_stitching import REST_SPEED
from policies.planners import IDMPlanner
from riskflow_env.agents.lane_graph import LaneGraph
from riskflow_env.cli_errors import run_script
from riskflow_env.config import EnvConfig
from riskflow_env.dynamics import SPEED, YAW
from riskflow_env.geometry import CENTRE, pairwise_overlap
from riskflow_env.metrics import kinematic_samples, offroad_counts
from riskflow_env.metrics.safety import footprint_sdf
from riskflow_env.scenarios import load_bank, shipped_bank
from riskflow_env.view import ScenePolicy

GENERATOR = "bits"  # the unguided generator as it ships
CURVED = ("roundabout", "racetrack", "u-turn", "intersection")
NO_FAMILY = "(no family)"  # e.g. recorded scenes: neither curved nor straight
STANDING = 0.5  # [m/s]
STANDS, STARTS = 0.5, 2.0  # [m] a vehicle at rest that the log moves less / more than this
HOLDS = (0.5, 1.0, 2.0)  # [m] holding distances the at-rest table tries
BUCKET = 20  # [steps] 2 s
FULL_EPISODES = EnvConfig(terminate_on_collision="none", terminate_on_offroad="none")


def open_loop(plans: np.ndarray, planned: np.ndarray, scene, drivable) -> tuple[bool, float]:
    """(any two plans overlap at some step, share of plan agent-steps with a footprint
    sample off the road) of one cycle's plans (A, T, 4), rows ``planned``."""
    states = plans[planned]
    length, width = scene.length[planned], scene.width[planned]
    xy, yaw = np.swapaxes(states[..., :2], 0, 1), np.swapaxes(states[..., YAW], 0, 1)
    overlap = pairwise_overlap(xy, yaw, length, width).any()
    outside = footprint_sdf(drivable, states, length, width) > 0
    road = offroad_counts(
        outside[..., CENTRE], outside.any(axis=-1), np.ones(states.shape[:2], bool)
    )
    return bool(overlap), road.footprint_rate


class FirstPlans:
    """A scene policy that drives as ``policy`` and keeps each episode's first plans:
    ``first = (plans (A, T, 4), planned (A,) non-ego rows with a plan)`` and the states
    they start from, ``start`` (A, 4)."""

    def __init__(self, policy: ScenePolicy) -> None:
        self.policy, self.first = policy, None

    def reset(self, view) -> None:
        self.policy.reset(view)
        self.first = None

    def act(self, view) -> dict:
        actions = self.policy.act(view)
        if self.first is None:
            planned = self.policy.plan_mask & view.active
            planned[0] = False
            self.first = (self.policy.plans.copy(), planned)
            self.start = view.current.copy()
        return actions


def at_rest_reach(plans, planned, start, scenario, rows) -> list[tuple[float, float]]:
    """``(plan reach, log reach)`` [m] of each planned vehicle at rest at the start whose
    log covers the plan's steps: the largest distance from its start position over the
    first plan, and over its logged positions at the same steps."""
    steps = plans.shape[1]
    now = scenario.current_index
    pairs = []
    for slot in np.flatnonzero(planned & (start[:, SPEED] <= REST_SPEED)):
        row = rows[slot]
        logged = scenario.states[row, now : now + steps + 1, :2]
        if scenario.valid[row, now : now + steps + 1].sum() < steps + 1:
            continue
        reach = np.linalg.norm(plans[slot, :, :2] - start[slot, :2], axis=-1).max()
        pairs.append((float(reach), float(np.linalg.norm(logged - logged[0], axis=-1).max())))
    return pairs


def past_road_end(record, off: np.ndarray) -> int:
    """How many of the off-road agent-steps ``off`` (A, S) (step ``s``: state ``s + 1``)
    lie past the end of a lane without successor, heading along it (within 0.6 rad): a
    vehicle that drove on where the map cuts its road. 0 on maps without lanes."""
    drivable = record.scenario.map
    if not off.any() or not drivable.lanes:
        return 0
    agents, steps = np.nonzero(off)
    states = record.states[agents, steps + 1]
    graph = LaneGraph(drivable)
    lane, s, _, heading_error = graph.match(states[:, :2], states[:, YAW])
    dead_end = graph.successors[lane, 0] < 0
    past = s >= graph.length[lane] - 1e-6  # the match clamps s to the lane
    return int(np.sum(dead_end & past & (np.abs(heading_error) < 0.6)))


def collision_kinds(record) -> Counter:
    """Counts of the episode's collision starts by (ego involved, kind, standing)."""
    counts = Counter()
    for event in record.events:
        if event["event"] != "collision_start":
            continue
        contact = sorted(event["contact"])
        kind = {("front", "front"): "head-on", ("front", "rear"): "rear-end"}.get(
            tuple(contact), "side"
        )
        slots = [record.agent_names.index(name) for name in event["agents"]]
        speeds = record.states[slots, event["step"], SPEED]
        who = "ego" if event["ego_involved"] else "non-ego"
        counts[(who, kind, "standing" if speeds.min() < STANDING else "moving")] += 1
    return counts


def diagnose(
    scenes: int,
    checkpoint: str | None,
    seed: int,
    bank: str | None = None,
    method: str = GENERATOR,
) -> dict:
    """Run the episodes of ``method`` (``bits`` or ``bits-raw``); returns per-family
    rows, collision kinds, time buckets, the at-rest vehicles' first-plan reach and
    per-family lateral accelerations (generated, logged)."""
    source = shipped_bank("eval") if bank is None else load_bank(bank)
    policy = make_policy(method, {"checkpoint": checkpoint} if checkpoint else {}, seed=seed)
    at_rest: list[tuple[float, float]] = []
    families: dict[str, list] = {}
    lateral: dict[str, list] = {}
    kinds: Counter = Counter()
    buckets = np.zeros((5, 2))  # off-road centroid steps, live steps per 2 s bucket
    recorder = FirstPlans(policy)
    with ClosedLoop(IDMPlanner(), recorder, config=FULL_EPISODES) as loop:
        for scenario in source.scenarios[:scenes]:
            record = loop.run(scenario)
            plan_overlap, plan_offroad = open_loop(*recorder.first, loop.base.scene, scenario.map)
            at_rest += at_rest_reach(
                *recorder.first, recorder.start, scenario, record.scenario_rows
            )
            live = record.active[:, :-1] & record.in_scene[:, 1:]
            live[0] = False  # the generator's vehicles only
            off = record.offroad_centroid[:, 1:] & live
            road = offroad_counts(
                record.offroad_centroid[:, 1:], record.offroad_footprint[:, 1:], live
            )
            rates = (road.centroid_rate, road.footprint_rate) if road.agent_steps else (0.0, 0.0)
            rates += (past_road_end(record, off) / max(road.agent_steps, 1),)
            steps = min(off.shape[1], len(buckets) * BUCKET)
            starts = np.arange(0, steps, BUCKET)
            buckets[: starts.size, 0] += np.add.reduceat(off[:, :steps].sum(0), starts)
            buckets[: starts.size, 1] += np.add.reduceat(live[:, :steps].sum(0), starts)
            episode = collision_kinds(record)
            kinds.update(episode)
            family = scenario.family or NO_FAMILY
            samples = kinematic_samples(rollout_record(scenario, record))
            lateral.setdefault(family, []).append(
                (
                    samples.generated["lateral_acceleration"],
                    samples.reference["lateral_acceleration"],
                )
            )
            families.setdefault(family, []).append(
                (
                    plan_overlap,
                    plan_offroad,
                    any(k[0] == "non-ego" for k in episode),
                    any(k[0] == "ego" for k in episode),
                    *rates,  # 0 for a scene without a generator vehicle
                )
            )
    return {
        "families": families, "kinds": kinds, "buckets": buckets, "at_rest": at_rest,
        "lateral": lateral,
    }  # fmt: skip


def grouped(rows: dict[str, list]) -> dict[str, list]:
    """Each family's entries, then the curved roads, the straight roads (the other named
    families) and all."""
    groups = dict(rows)
    groups["curved roads"] = [r for name in CURVED for r in rows.get(name, [])]
    straight = [name for name in rows if name not in (*CURVED, NO_FAMILY)]
    groups["straight roads"] = [r for name in straight for r in rows[name]]
    groups["all"] = [r for name in rows for r in rows[name]]
    return groups


def _p95(values: list[np.ndarray]) -> float:
    pooled = np.abs(np.concatenate(values)) if values else np.zeros(0)
    return float(np.percentile(pooled, 95)) if pooled.size else float("nan")


def report(result: dict) -> str:
    """Markdown tables of :func:`diagnose`'s result."""
    lines = [
        "| family | scenes | one-shot plans overlap | one-shot plan footprint off-road | "
        "closed loop: non-ego collision | ego collision | off-road centroid | footprint | "
        "centroid past a road's end |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, entries in grouped(result["families"]).items():
        if not entries:
            continue
        values = np.array(entries, dtype=float).mean(axis=0)
        lines.append(
            f"| {name} | {len(entries)} | {values[0]:.2f} | {values[1]:.3f} | {values[2]:.2f} "
            f"| {values[3]:.2f} | {values[4]:.3f} | {values[5]:.3f} | {values[6]:.3f} |"
        )
    lines += ["", "| collision starts | kind | vehicles | count |", "| --- | --- | --- | ---: |"]
    for (who, kind, standing), count in sorted(result["kinds"].items()):
        lines.append(f"| {who} | {kind} | {standing} | {count} |")
    lines += ["", "| time [s] | off-road centroid share (generator's vehicles) |", "| --- | ---: |"]
    for index, (off, live) in enumerate(result["buckets"]):
        if live:
            lines.append(f"| {2 * index}-{2 * index + 2} | {off / live:.3f} |")
    holds = " | ".join(f"held at {d:g} m" for d in HOLDS)
    lines += [
        "",
        "| at rest at the start, in the log | vehicles | plan reach p50 / p90 / p95 [m] | "
        f"{holds} |",
        "| --- | ---: | ---: | " + " | ".join("---:" for _ in HOLDS) + " |",
    ]
    reach = np.array(result["at_rest"], dtype=float).reshape(-1, 2)
    for name, rows in (
        (f"stands (< {STANDS:g} m)", reach[reach[:, 1] < STANDS, 0]),
        (f"starts (> {STARTS:g} m)", reach[reach[:, 1] > STARTS, 0]),
    ):
        if rows.size:
            p50, p90, p95 = np.percentile(rows, [50, 90, 95])
            held = " | ".join(f"{np.mean(rows < d):.3f}" for d in HOLDS)
            lines.append(f"| {name} | {rows.size} | {p50:.2f} / {p90:.2f} / {p95:.2f} | {held} |")
    lines += [
        "",
        "| family | p95 lateral acceleration: generator [m/s^2] | its log [m/s^2] |",
        "| --- | ---: | ---: |",
    ]
    for name, entries in grouped(result["lateral"]).items():
        if entries:
            generated, logged = zip(*entries, strict=True)
            lines.append(f"| {name} | {_p95(list(generated)):.2f} | {_p95(list(logged)):.2f} |")
    return "\n".join(lines)


@dataclass(frozen=True)
class Options:
    """Benchmark options."""

    scenes: int = 21
    """first N scenes of the bank (at least 1; fewer if the bank has fewer)"""
    checkpoint: str | None = None
    """generator checkpoint (default: the shipped one)"""
    seed: int = 0
    """noise seed of the generator"""
    bank: str | None = None
    """scene folder (riskflow_env.scenarios.load_bank); default: the shipped evaluation bank"""
    raw: bool = False
    """also bits-raw (the raw generator, without the rule layer), its tables after bits'"""

    def __post_init__(self) -> None:
        if self.scenes < 1:
            raise ValueError(f"--scenes must be >= 1, got {self.scenes}")
        check_seeds((self.seed,), "--seed")


PROG = "realism_diagnosis.py"  # the name in usage and error lines


def main(argv: list[str] | None = None) -> str:
    """Entry point: run, print and return the tables."""
    args = parse_dataclass(Options, argv, prog=PROG, description=__doc__.split("\n")[0], debug=True)
    start = time.perf_counter()
    sections = []
    for method in with_raw((GENERATOR,), args.raw):
        result = diagnose(args.scenes, args.checkpoint, args.seed, args.bank, method)
        sections.append(f"### {method}\n\n{report(result)}")
    text = "\n\n".join(sections)
    count = sum(len(rows) for rows in result["families"].values())
    print(text)
    print(f"\n{count} scenes in {time.perf_counter() - start:.0f} s")
    return text


if __name__ == "__main__":
    run_script(PROG, main)
