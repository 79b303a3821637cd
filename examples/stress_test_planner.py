"""Stress-test an ego planner: RiskFlow drives everyone else and looks for its failures.

    python examples/stress_test_planner.py                        # IDM ego, 20 scenes
    python examples/stress_test_planner.py --planner my_planner --scenes 50 --k all

Plug in your own planner: a function from the ego's observation (and, if it needs more,
the read-only scene view) to an action::

    def my_planner(observation: np.ndarray, view: SceneView) -> np.ndarray:
        speed = observation[0]                     # layout: riskflow_env/observations.py
        return np.array([accel, yaw_rate])         # [m/s^2], [rad/s]

A planner object may also have ``reset(view)``, called at the start of every episode.
Edit :func:`my_planner` below and run with ``--planner my_planner``, or import
:class:`policies.harness.ClosedLoop` and pass your function to it.

Each scene of the shipped evaluation bank runs closed loop for up to 10 s (the episode ends
when the ego collides or leaves the road). The report gives the ego's collision rate, the
time to its first collision and its off-road rate, with 95% confidence intervals (Wilson
for rates, bootstrap for mean times), and the worst scenes found (ego collisions first,
then the closest calls). Those are saved in ``<out>/worst/`` as scenario files whose
reference future is what happened. Watch one again (the others replay what they did, the
IDM ego drives) with::

    python examples/rollout.py --scenario outputs/stress_test/worst/00-<name>.npz --traffic replay

or put your planner back in the same situation::

    scenario = load_scenario("outputs/stress_test/worst/00-<name>.npz")
    with ClosedLoop(my_planner, ReplayPolicy(mode="open_loop")) as loop:
        record = loop.run(scenario)

``<out>/summary.json`` holds the summary and every scene's metrics; ``<out>/events.jsonl``
the event log of all scenes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from policies.dataclass_cli import parse_dataclass
from policies.harness import ClosedLoop, EpisodeRecord, summarize
from policies.planners import PLANNERS, EgoPlanner, make_planner
from policies.riskflow import RiskFlowAdversary
from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import save_scenario, shipped_bank
from riskflow_env.view import SceneView

CRUISE_SPEED = 12.0  # [m/s] my_planner's desired speed
TIME_GAP = 1.5  # [s] my_planner's time gap to the vehicle ahead


def my_planner(observation: np.ndarray, view: SceneView) -> np.ndarray:
    """An example planner that reads only the ego's observation; replace it with yours.

    Speed: track ``CRUISE_SPEED``, and brake when a vehicle in a 4 m wide corridor ahead
    is closer than 2 m plus ``TIME_GAP`` seconds of travel. Steering: turn away from the
    nearer road edge, comparing the map SDF 10 m ahead, 30 degrees to either side.

    Args:
        observation: (142,) the ego's observation (default ``ObservationConfig``): own
            features (speed [m/s], accel, yaw rate, length, width, SDF), 8 neighbours x
            (dx, dy, cos, sin, dvx, dvy, normalised distance, TTC risk, length, width,
            present) in the ego's frame, then 12 directions x 4 distances of map SDF [m].
        view: the scene (unused here).

    Returns:
        (2,) (accel [m/s^2], yaw rate [rad/s]).
    """
    speed, length = observation[0], observation[3]
    neighbours = observation[6 : 6 + 8 * 11].reshape(8, 11)
    dx, dy, present = neighbours[:, 0], neighbours[:, 1], neighbours[:, 10] > 0
    ahead = present & (dx > 0) & (np.abs(dy) < 2.0)
    gap = np.min(dx[ahead] - 0.5 * (length + neighbours[ahead, 8]), initial=np.inf)
    accel = 0.5 * (CRUISE_SPEED - speed)
    if gap < 2.0 + TIME_GAP * speed:
        accel = -6.0 * (1.0 - max(gap, 0.0) / (2.0 + TIME_GAP * speed))
    rays = observation[6 + 8 * 11 :].reshape(12, 4)  # direction k at 30 k deg, left positive
    yaw_rate = 0.1 * (rays[11, 2] - rays[1, 2])  # right edge nearer (SDF higher): turn left
    return np.array([np.clip(accel, -8.0, 2.0), np.clip(yaw_rate, -0.5, 0.5)])


@dataclass(frozen=True)
class Options:
    """Options of ``stress_test_planner.py``."""

    planner: str = "idm"
    """ego planner: idm, lane_keeping, sampling_mpc, constant_velocity or my_planner (edit it
    in this file)"""
    scenes: int = 20
    """scenes of the shipped evaluation bank to run (the first N, 105 at most)"""
    k: str = "5"
    """size of the adversary's controllable set A_c: an int >= 0 or 'all'"""
    planning_interval: float = 0.5
    """time between re-plans of the adversary [s]"""
    target: str = "ego"
    """what A_c is pulled toward: 'ego' (stress testing) or 'others' (the paper's)"""
    seed: int = 0
    """noise seed of the adversary"""
    steps: int = 100
    """episode length [steps of 0.1 s]"""
    worst: int = 3
    """worst scenes to save as scenario files"""
    out: Path = Path("outputs/stress_test")
    """output directory"""
    device: str = "cpu"
    """torch device of the generator"""
    checkpoint: Path | None = None
    """generator checkpoint; default the shipped policies/checkpoints/riskflow_default.pt"""

    def __post_init__(self) -> None:
        choices = (*PLANNERS, "my_planner")
        if self.planner not in choices:
            raise ValueError(f"--planner must be one of {choices}, got {self.planner!r}")
        if not (self.k == "all" or self.k.isdigit()):
            raise ValueError(f"--k must be an int >= 0 or 'all', got {self.k!r}")
        if self.scenes < 1 or self.steps < 1 or self.worst < 0:
            raise ValueError("--scenes and --steps must be >= 1, --worst >= 0")


def planner_named(name: str, config: EnvConfig) -> EgoPlanner:
    """A built-in planner by name (with the env's dynamics bounds), or :func:`my_planner`."""
    return my_planner if name == "my_planner" else make_planner(name, config.dynamics)


def make_adversary(options: Options) -> RiskFlowAdversary:
    """The RiskFlow adversary of the options (shipped checkpoint unless ``--checkpoint``)."""
    return RiskFlowAdversary(
        k=options.k if options.k == "all" else int(options.k),
        planning_interval=options.planning_interval,
        target=options.target,
        seed=options.seed,
        device=options.device,
        checkpoint=options.checkpoint,
    )


def severity(record: EpisodeRecord) -> tuple:
    """Sort key, worst first: ego collisions (earliest first), then the closest calls."""
    metrics = record.metrics
    collided = metrics["ego_collided"]
    when = metrics["time_to_first_ego_collision"] if collided else np.inf
    distance = metrics["min_distance_to_ego"]
    return (not collided, when, np.inf if distance is None else distance, metrics["scenario"])


def report(summary: dict[str, dict]) -> str:
    """The summary as a small table."""
    rows = [
        ("ego collision rate", "ego_collision_rate", "{:.1%}"),
        ("any collision rate", "collision_rate", "{:.1%}"),
        ("ego off-road rate", "ego_offroad_rate", "{:.1%}"),
        ("time to 1st ego collision [s]", "time_to_first_ego_collision", "{:.2f}"),
        ("min distance to ego [m]", "min_distance_to_ego", "{:.2f}"),
        ("planning time per cycle [ms]", "planning_time_ms", "{:.1f}"),
    ]
    lines = []
    for label, key, fmt in rows:
        entry = summary[key]
        value = "n/a" if entry["value"] is None else fmt.format(entry["value"])
        interval = (
            ""
            if entry["low"] is None
            else f"[{fmt.format(entry['low'])}, {fmt.format(entry['high'])}]"
        )
        lines.append(f"  {label:32s} {value:>8}  {interval:20s} n = {entry['n']}")
    return "\n".join(lines)


def main(options: Options) -> dict[str, Any]:
    """Run the scenes, print the report, save the worst scenes; returns the summary."""
    bank = shipped_bank("eval")
    if options.scenes > len(bank):
        raise SystemExit(f"--scenes {options.scenes}: the shipped bank has {len(bank)} scenes")
    config = EnvConfig(episode_steps=options.steps)
    planner = planner_named(options.planner, config)
    out = options.out
    out.mkdir(parents=True, exist_ok=True)
    with ClosedLoop(
        planner,
        make_adversary(options),
        config=config,
        event_log=out / "events.jsonl",
        event_log_mode="overwrite",  # a fresh run of the whole script
    ) as loop:
        records = [loop.run(bank[i]) for i in tqdm(range(options.scenes), desc="scenes")]
    summary = summarize(records)
    print(f"planner {options.planner!r} vs RiskFlow (K={options.k}, target={options.target}):")
    print(report(summary))
    ranked = sorted(records, key=severity)[: options.worst]
    worst = []
    print("worst scenes:")
    for rank, record in enumerate(ranked):
        metrics = record.metrics
        path = out / "worst" / f"{rank:02d}-{metrics['scenario']}.npz"
        save_scenario(record.to_scenario(), path)
        worst.append({"file": str(path), **metrics})
        if metrics["ego_collided"]:
            outcome = f"ego collision at {metrics['time_to_first_ego_collision']:.1f} s"
        else:
            outcome = f"closest call {metrics['min_distance_to_ego'] or np.inf:.2f} m"
        print(f"  {rank}. {metrics['scenario']:28s} {outcome:28s} -> {path}")
    result = {
        "options": {key: str(value) for key, value in vars(options).items()},
        "summary": summary,
        "worst": worst,
        "scenes": [record.metrics for record in records],
    }
    (out / "summary.json").write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out / 'summary.json'}, {out / 'events.jsonl'}")
    return result


if __name__ == "__main__":
    main(
        parse_dataclass(Options, prog="stress_test_planner.py", description=__doc__.splitlines()[0])
    )
