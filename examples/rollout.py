"""One 10 s closed-loop episode: the IDM ego planner against the RiskFlow adversary.

    python examples/rollout.py                          # shipped scene 0, K = 5, target ego
    python examples/rollout.py --scenario 12 --k all --target others --video mp4
    python examples/rollout.py --scenario sd_scene.pkl --traffic replay   # a recorded log
    python examples/rollout.py --scenario outputs/stress/failures/<scene>-seed0.npz \\
        --traffic replay --replay-mode open_loop        # a failure's scene, its own future

The ego follows its lane with IDM (``policies.planners.IDMPlanner``); every other vehicle
is driven by ``RiskFlowAdversary`` (the shipped checkpoint unless ``--checkpoint``): one
generator pass plans 5 s for every vehicle, the top-K critical ones (``A_c``) are guided
toward risky interactions, and it re-plans every ``--planning-interval`` seconds. The
adversary runs with its defaults, the realistic base of docs/explanation/realism.md (20 avoidance
steps pull the base plans apart and onto the road, parked cars within 4 m of rest keep
standing, new plans blended into the executed ones first) with the map term weighted 20
(the guided vehicles keep to the road while they attack); ``--avoid-steps 0
--hold-distance 0`` is the raw generator. With
``--traffic replay`` the others replay the scenario's reference future instead, without
reacting to the ego: ``--replay-mode tracking`` (the default, ``ReplayPolicy``'s) steers
them onto the logged positions, which a recorded log (not drawn from these dynamics) needs
(inverse dynamics drift recorded vehicles off the road); ``--replay-mode open_loop``
reproduces a future that this env simulated (an exported episode) exactly, where
tracking is off by up to about 2 m on tight curves.

Prints the events (collisions, off-road excursions) and the metrics; writes to ``--out``
(default ``outputs/rollout/``): ``rollout.gif`` (or ``.mp4``) with the plans drawn (cyan:
base plans; purple, haloed vehicles: guided plans of ``A_c``; red: collisions; amber:
off-road; a legend on the frame), ``events.jsonl`` (the event log,
``riskflow_env.wrappers.read_event_log`` reads it) and ``metrics.json``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from policies import harness
from policies.cli_inputs import check_device
from policies.dataclass_cli import check_at_least, run_main
from policies.harness import METRICS, ClosedLoop
from policies.learned.adversary_config import AdversaryConfig, check_planning_interval
from policies.learned.checkpoint import CheckpointError
from policies.learned.plan_avoidance import DEFAULT_AVOID_STEPS
from policies.planners import IDMPlanner
from policies.riskflow import RiskFlowAdversary
from riskflow_env.agents import ReplayPolicy
from riskflow_env.agents.replay import REPLAY_MODES
from riskflow_env.atomic_files import write_text
from riskflow_env.config import EnvConfig
from riskflow_env.folder_lock import make_output_folder
from riskflow_env.scenarios import Scenario, load_scenario, shipped_bank
from riskflow_env.scenarios.scenarionet import load_scenarionet

VIDEO_FORMATS = ("gif", "mp4", "none")
TRAFFIC = ("riskflow", "replay")


@dataclass(frozen=True)
class Options:
    """Options of ``rollout.py``."""

    scenario: str = "0"
    """shipped evaluation bank index (0-104), or a scenario file (.npz or ScenarioNet .pkl)"""
    k: str = "5"
    """size of the controllable set A_c: an int >= 0 (0: unguided generator) or 'all'"""
    planning_interval: float = 0.5
    """time between re-plans of the adversary [s], a multiple of 0.1 s up to 5.2 s"""
    target: str = "ego"
    """what A_c is pulled toward: 'ego' (stress testing the ego) or 'others' (the paper's)"""
    seed: int = 0
    """noise seed of the adversary (same seed, same rollout)"""
    out: Path = Path("outputs/rollout")
    """output directory"""
    device: str = "cpu"
    """torch device of the generator ('cpu', 'cuda', ...)"""
    checkpoint: Path | None = None
    """generator checkpoint; default the shipped policies/checkpoints/riskflow_default.pt"""
    video: str = "gif"
    """video format: gif, mp4 or none"""
    steps: int = 100
    """episode length [steps of 0.1 s]"""
    traffic: str = "riskflow"
    """who drives the other vehicles: 'riskflow' or 'replay' (the scenario's future)"""
    replay_mode: str = "tracking"
    """with --traffic replay: 'tracking' (position feedback: stays on a recorded log's
    positions) or 'open_loop' (inverse dynamics: reproduces a future this env simulated,
    such as an exported episode, exactly)"""
    avoid_steps: int = DEFAULT_AVOID_STEPS
    """avoidance steps on the base plans (RiskFlowAdversary avoid_steps; 0: off)"""
    hold_distance: float = AdversaryConfig.hold_distance
    """[m] vehicles at rest whose plan moves them less keep standing (0: off)"""
    lambda_map: float = AdversaryConfig.lambda_map
    """weight of the guidance's map term"""

    def __post_init__(self) -> None:
        if self.video not in VIDEO_FORMATS:
            raise ValueError(f"--video must be one of {VIDEO_FORMATS}, got {self.video!r}")
        if self.traffic not in TRAFFIC:
            raise ValueError(f"--traffic must be one of {TRAFFIC}, got {self.traffic!r}")
        if self.replay_mode not in REPLAY_MODES:
            raise ValueError(
                f"--replay-mode must be one of {REPLAY_MODES}, got {self.replay_mode!r}"
            )
        if self.target not in ("others", "ego"):
            raise ValueError(f"--target must be 'others' or 'ego', got {self.target!r}")
        if not (self.k == "all" or (self.k.isdigit())):
            raise ValueError(f"--k must be an int >= 0 or 'all', got {self.k!r}")
        check_planning_interval(self.planning_interval)
        check_at_least(self, {"steps": 1, "seed": 0})
        check_device(self.device)
        if not 0 <= self.lambda_map < float("inf"):
            raise ValueError(f"--lambda-map must be finite and >= 0, got {self.lambda_map}")
        if self.avoid_steps < 0:
            raise ValueError(f"--avoid-steps must be >= 0, got {self.avoid_steps}")
        if not 0 <= self.hold_distance < float("inf"):
            raise ValueError(f"--hold-distance must be finite and >= 0, got {self.hold_distance}")

    @property
    def controllable(self) -> int | str:
        """``k`` as the adversary takes it."""
        return self.k if self.k == "all" else int(self.k)


def load_scene(spec: str) -> Scenario:
    """Scene ``spec``: an index into the shipped evaluation bank or a scenario file."""
    if spec.lstrip("-").isdigit():
        bank = shipped_bank("eval")
        index = int(spec)
        if not 0 <= index < len(bank):
            raise ValueError(f"--scenario {spec}: the shipped bank has scenes 0-{len(bank) - 1}")
        return bank[index]
    path = Path(spec)
    if not spec.strip():
        raise ValueError("--scenario is empty: give a shipped bank index or a scenario file")
    if path.is_dir():
        raise ValueError(f"--scenario {spec!r} is a folder; give one scenario file or a bank index")
    if not path.is_file():
        raise ValueError(f"--scenario {spec!r}: no such scenario file (or give a bank index)")
    suffix = path.suffix.lower()
    if suffix not in (".npz", ".pkl"):
        raise ValueError(
            f"--scenario {spec!r}: unknown scenario format {suffix or '(no suffix)'!r}; expected "
            "a bank index, a RiskFlow scenario file (.npz) or a ScenarioNet pickle (.pkl)"
        )
    try:
        return load_scenarionet(path) if suffix == ".pkl" else load_scenario(path)
    except (ValueError, KeyError, OSError) as err:  # a file of that suffix it cannot read
        raise ValueError(f"--scenario {spec!r}: {err}") from None


def make_traffic(options: Options) -> RiskFlowAdversary | ReplayPolicy:
    """The scene policy of every vehicle but the ego."""
    if options.traffic == "replay":
        return ReplayPolicy(controlled="others", mode=options.replay_mode)
    try:
        return RiskFlowAdversary(
            k=options.controllable,
            planning_interval=options.planning_interval,
            target=options.target,
            seed=options.seed,
            device=options.device,
            checkpoint=options.checkpoint,
            avoid_steps=options.avoid_steps,
            hold_distance=options.hold_distance,
            lambda_map=options.lambda_map,
        )
    except (CheckpointError, FileNotFoundError, IsADirectoryError) as err:  # no such file
        raise ValueError(f"--checkpoint: {err}") from None


def describe(event: dict[str, Any]) -> str:
    """One line of the event log, for people."""
    kind, head = event["event"], f"  t = {event['time']:4.1f} s  "
    if kind == "collision_start":
        a, b = event["agents"]
        contact = "/".join(event["contact"])
        return f"{head}collision   {a} <-> {b}  {event['relative_speed']:.1f} m/s ({contact})"
    if kind == "collision_end":
        a, b = event["agents"]
        return f"{head}  ends      {a} <-> {b}  after {event['duration']:.1f} s ({event['cause']})"
    if kind == "offroad_start":
        share, depth = event["offroad_fraction"], event["sdf_depth"]
        return f"{head}off-road    {event['agent']}  {share:.0%} of footprint, {depth:.2f} m out"
    if kind == "offroad_end":
        agent, duration = event["agent"], event["duration"]
        return f"{head}  ends      {agent}  after {duration:.1f} s ({event['cause']})"
    return f"{head}{kind}: {event.get('end_reason', '')}"


def warm_up(options: Options, scenario: Scenario, config: EnvConfig) -> None:
    """One untimed step with a throwaway adversary (:func:`policies.harness.warm_up`, as
    ``riskflow-eval`` does), so that the one-off costs stay out of the episode's planning
    times."""
    if options.traffic != "riskflow":
        return
    print("warm-up (the first model call; on a new install also compiling the kernels, about "
          "half a minute once) ...", end="", flush=True)  # fmt: skip
    planner = IDMPlanner(dynamics=config.dynamics)
    seconds = harness.warm_up(planner, make_traffic(options), scenario, config)
    print(f" {seconds:.1f} s")


def main(options: Options) -> dict[str, Any]:
    """Run the episode, print it, write the outputs; returns the metrics."""
    scenario = load_scene(options.scenario)
    traffic = make_traffic(options)
    out = make_output_folder(options.out, "--out")
    video = None if options.video == "none" else out / f"rollout.{options.video}"
    config = EnvConfig(episode_steps=options.steps)
    print(f"scene {scenario.name!r} ({scenario.num_agents} vehicles), traffic: {options.traffic}")
    warm_up(options, scenario, config)
    with ClosedLoop(
        IDMPlanner(dynamics=config.dynamics),
        traffic,
        config=config,
        event_log=out / "events.jsonl",
        event_log_mode="overwrite",  # a fresh run of the whole script
        video=video,
    ) as loop:
        record = loop.run(scenario)
    write_text(out / "metrics.json", json.dumps(record.metrics, indent=2) + "\n")
    print("events:")
    for event in record.events[:-1]:
        print(describe(event))
    if len(record.events) <= 1:
        print("  none")
    metrics = record.metrics
    why = (
        "ego collided"
        if metrics["ego_collided"]
        else "ego off-road"
        if metrics["ego_offroad"]
        else "time limit"
    )
    print(f"episode over after {metrics['steps'] * record.dt:.1f} s ({why})")
    print("metrics:")
    for name, value in metrics.items():
        if name == "scenario":
            continue
        shown = f"{value:.3f}" if isinstance(value, float) else value
        print(f"  {name:28s} {shown!s:>10}   {METRICS[name]}")
    written = [out / "events.jsonl", out / "metrics.json"] + ([video] if video else [])
    print("wrote", ", ".join(str(path) for path in written))
    return record.metrics


if __name__ == "__main__":
    run_main(main, Options, "rollout.py", __doc__.splitlines()[0])
