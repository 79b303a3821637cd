"""Closed-loop runs: an ego planner under test and a scene policy driving one env.

The loop, written once for the examples and the evaluations::

    reset(scenario)      planner.reset(view); policy.reset(view)
    every step           actions = policy.act(view)           # every live vehicle but the ego
                         policy.draw(video.renderer)          # plans on the frame, if recording
                         actions["ego"] = planner(observation["ego"], view)
                         env.step(actions)

Every run goes through an :class:`~riskflow_env.wrappers.EventLogWrapper` (JSON Lines on
disk with ``event_log=``, in memory otherwise) and, with ``video=``, a
:class:`~riskflow_env.wrappers.VideoRecorder`. Each episode gives an :class:`EpisodeRecord`:
the executed states, the events and the metrics of :data:`METRICS` (the off-road rates are
:func:`riskflow_env.metrics.offroad_counts` over the episode's live agent-steps, with the
env's own off-road flags; the evaluation's ORR counts a record's scored agent-steps instead,
see :mod:`riskflow_env.metrics.safety`); :meth:`EpisodeRecord.to_scenario` turns it into a
scenario whose reference future is what was executed, so that
:class:`~policies.baselines.ReplayPolicy` replays it. :func:`summarize` aggregates records
with 95% confidence intervals; :func:`warm_up` keeps one-off costs out of the timings.

Episodes end as ``config`` says; the default :class:`~riskflow_env.config.EnvConfig`
ends an episode when the ego collides or leaves the road, or after 10 s, and freezes both
vehicles of every collision where they touched. :mod:`policies.stress.failures` analyses
a record's ego collisions (type, avoidability, the attacker's kinematics).
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from policies.planners.base import EgoPlanner, as_action, reset_planner
from policies.statistics import mean_summary, rate
from riskflow_env.config import EnvConfig
from riskflow_env.dynamics import YAW
from riskflow_env.env import RiskFlowParallelEnv
from riskflow_env.geometry import separation
from riskflow_env.metrics import RolloutRecord, offroad_counts
from riskflow_env.render import RenderConfig
from riskflow_env.scenarios import Scenario, ScenarioSource
from riskflow_env.view import ScenePolicy, SceneView
from riskflow_env.wrappers import EventLogWrapper, VideoRecorder

EGO = "ego"
METRICS = {
    "scenario": "scenario name",
    "steps": "env steps run",
    "collisions": "collision events (any pair)",
    "ego_collided": "the ego collided",
    "time_to_first_collision": "[s] first collision of any pair, None if none",
    "time_to_first_ego_collision": "[s] first collision of the ego, None if none",
    "offroad_events": "off-road events (any vehicle)",
    "ego_offroad": "the ego left the road (a footprint sample off the drivable area)",
    "orr_centroid": "share of live agent-steps (every vehicle while controlled, the ego "
    "included) with the centre off the road (paper ORR)",
    "orr_footprint": "share of live agent-steps with a footprint sample off the road",
    "min_distance_to_ego": "[m] least box separation between the ego and another vehicle "
    "(<= 0: in contact; None: no other vehicle)",
    "planning_cycles": "scene-policy calls that planned (every call for reactive policies)",
    "planning_time_ms": "[ms] mean wall time of a planning cycle (None: no cycle)",
    "planning_time_max_ms": "[ms] longest planning cycle",
    "ego_time_ms": "[ms] mean wall time of a planner call",
}


@dataclass(frozen=True)
class EpisodeRecord:
    """One closed-loop episode.

    Attributes:
        scenario: the scenario it started from.
        scenario_rows: (A,) row of each slot in ``scenario.states`` (-1: empty slot).
        agent_names: (A,) slot names, ``"ego"`` first.
        states: (A, S + 1, 4) executed states (x [m], y [m], v [m/s], psi [rad]) from the
            reset (index 0) to the last of the S steps.
        in_scene: (A, S + 1) bool, the vehicle was in the scene at that step: False for
            empty slots and from the step a vehicle left on (``EnvConfig.
            leave_when_log_ends``); a vehicle that is done but stays (a collision, the
            end of the episode) is still in the scene.
        active: (A, S + 1) bool, the vehicle was live (still controlled).
        offroad_centroid: (A, S + 1) bool, centre off the drivable area.
        offroad_footprint: (A, S + 1) bool, a footprint sample off the drivable area.
        events: the episode's rows of the event log (``episode_summary`` last).
        metrics: :data:`METRICS` of the episode.
        dt: time step [s].
        guided: (A, S + 1) bool, the vehicle was in the scene policy's controllable set
            ``A_c`` when it chose the action of step ``s`` (the last column repeats the
            one before); None when the policy has no ``controllable`` (e.g. IDM, replay).
    """

    scenario: Scenario
    scenario_rows: np.ndarray
    agent_names: tuple[str, ...]
    states: np.ndarray
    in_scene: np.ndarray
    active: np.ndarray
    offroad_centroid: np.ndarray
    offroad_footprint: np.ndarray
    events: tuple[dict[str, Any], ...]
    metrics: dict[str, Any] = field(default_factory=dict)
    dt: float = 0.1
    guided: np.ndarray | None = None

    @property
    def present(self) -> np.ndarray:
        """(A,) bool, slots holding a vehicle at the reset (vehicles may leave the scene,
        none enters it)."""
        return self.in_scene[:, 0]

    def rollout_record(self, history: int = 2) -> RolloutRecord:
        """The episode as a :class:`riskflow_env.metrics.RolloutRecord` (SCR, ORR, ADE,
        KDD, WOSAC...), with ``history`` logged steps prepended as context."""
        return RolloutRecord.from_scenario(
            self.scenario, self.states, self.in_scene, self.scenario_rows, history=history
        )

    def to_scenario(self, name: str | None = None) -> Scenario:
        """The episode as a scenario: the starting history of the vehicles that had a slot
        (slot order, the ego first) followed by the executed states as the reference
        future (padded with invalid steps to the original future length; invalid from
        the step a vehicle left the scene on)."""
        source, slots = self.scenario, np.flatnonzero(self.present)
        rows, history = self.scenario_rows[slots], source.current_index + 1
        executed = self.states[slots, 1:]
        future = max(executed.shape[1], source.future_steps)
        states = np.zeros((slots.size, history + future, 4))
        valid = np.zeros(states.shape[:2], dtype=bool)
        states[:, :history] = source.states[rows, :history]
        valid[:, :history] = source.valid[rows, :history]
        states[:, history : history + executed.shape[1]] = executed
        valid[:, history : history + executed.shape[1]] = self.in_scene[slots, 1:]

        def pick(labels: tuple[str, ...]) -> tuple[str, ...]:
            return tuple(labels[row] for row in rows) if labels else ()

        return Scenario(
            map=source.map,
            states=states,
            valid=valid,
            length=source.length[rows],
            width=source.width[rows],
            ego_index=0,
            agent_ids=pick(source.agent_ids),
            name=name or f"{source.name}-closed-loop",
            dt=source.dt,
            history_steps=history,
            kinds=pick(source.kinds),
            source=source.source,
            family=source.family,
        )


class ClosedLoop:
    """Runs episodes of ``planner`` (the ego) against ``policy`` (everyone else).

    Args:
        planner: the ego planner, ``planner(observation, view) -> (2,) action``.
        policy: the scene policy of the other vehicles (e.g. ``RiskFlowAdversary``);
            with ``video``, its ``draw(renderer)`` (if any) is called every step.
        config: env configuration (episode length, termination rules).
        scenarios: where ``run(None)`` draws scenes from; default the shipped bank.
        event_log: JSON Lines file of the events of every episode; None: in memory.
        event_log_mode: ``"new"`` (a non-empty existing file raises FileExistsError),
            ``"append"`` or ``"overwrite"``.
        video: video file (``.gif`` or ``.mp4``, ``{episode}`` for one file per
            episode); None records nothing.
        render_config: view of the video frames.
    """

    def __init__(
        self,
        planner: EgoPlanner,
        policy: ScenePolicy,
        config: EnvConfig | None = None,
        scenarios: ScenarioSource | Scenario | None = None,
        event_log: str | os.PathLike | None = None,
        event_log_mode: str = "new",
        video: str | os.PathLike | None = None,
        render_config: RenderConfig | None = None,
    ) -> None:
        if not callable(planner):
            raise TypeError(
                f"planner must be callable (observation, view) -> action, got {planner!r}"
            )
        if not isinstance(policy, ScenePolicy):
            raise TypeError(
                f"policy must be a ScenePolicy (reset, act), got {type(policy).__name__}"
            )
        self.planner, self.policy = planner, policy
        self.base = RiskFlowParallelEnv(config=config, scenarios=scenarios)
        env: Any = self.base
        self.video = None if video is None else VideoRecorder(env, video, config=render_config)
        if event_log_mode not in ("new", "append", "overwrite"):
            raise ValueError(
                f"event_log_mode must be 'new', 'append' or 'overwrite', got {event_log_mode!r}"
            )
        try:
            self.env = EventLogWrapper(
                self.video or env,
                event_log,
                append=event_log_mode == "append",
                overwrite=event_log_mode == "overwrite",
            )
        except BaseException:  # e.g. an existing log refused: leave nothing open
            (self.video or env).close()
            raise
        self.records: list[EpisodeRecord] = []

    def __enter__(self) -> ClosedLoop:
        return self

    def __exit__(self, exc_type: Any, exc: Any, traceback: Any) -> None:
        self.env.close("close" if exc_type is None else "exception")

    def close(self) -> None:
        """Finish the event log and the video, close the env."""
        self.env.close()

    def run(self, scenario: Scenario | None = None, seed: int | None = None) -> EpisodeRecord:
        """One episode from ``scenario`` (None: drawn from the env's source with ``seed``)."""
        env, base, policy = self.env, self.base, self.policy
        first_event = len(env.events)
        options = None if scenario is None else {"scenario": scenario}
        observations, _ = env.reset(seed=seed, options=options)
        view = base.view()
        reset_planner(self.planner, view)
        policy.reset(view)
        draw = getattr(policy, "draw", None) if self.video is not None else None
        frames = [_frame(base)]
        cycle_times, ego_times, guided = [], [], []
        while env.agents:
            view = base.view()
            cycles, start = getattr(policy, "cycles", None), time.perf_counter()
            actions = dict(policy.act(view))
            elapsed = time.perf_counter() - start
            if cycles is None or getattr(policy, "cycles", None) != cycles:
                cycle_times.append(elapsed)
            guided.append(controllable_now(policy, view.num_agents))
            if draw is not None:
                draw(self.video.renderer)
            if EGO in env.agents:
                start = time.perf_counter()
                actions[EGO] = as_action(self.planner(observations[EGO], view))
                ego_times.append(time.perf_counter() - start)
            observations, *_ = env.step(actions)
            frames.append(_frame(base))
        record = _record(base, frames, tuple(env.events[first_event:]))
        record.metrics.update(planning_metrics(cycle_times, ego_times))
        record = dataclasses.replace(record, guided=guided_frames(guided))
        self.records.append(record)
        return record


def warm_up(
    planner: EgoPlanner, policy: ScenePolicy, scenario: Scenario, config: EnvConfig, seed: int = 0
) -> float:
    """One untimed step of ``scenario`` with a throwaway ``policy``: one-off costs (the first
    model call, compiling the kernels) stay out of later planning times. Its time [s]."""
    start = time.perf_counter()
    with ClosedLoop(planner, policy, dataclasses.replace(config, episode_steps=1)) as loop:
        loop.run(scenario, seed=seed)
    return time.perf_counter() - start


def controllable_now(policy: ScenePolicy, num_agents: int) -> np.ndarray | None:
    """(A,) copy of the policy's ``A_c`` after ``act`` (None if it has none)."""
    controllable = getattr(policy, "controllable", None)
    if controllable is None or np.shape(controllable) != (num_agents,):
        return None
    return np.array(controllable, dtype=bool)


def guided_frames(flags: list[np.ndarray | None]) -> np.ndarray | None:
    """An episode's :attr:`EpisodeRecord.guided` (A, S + 1) from the S per-step
    :func:`controllable_now` (None when the policy had no ``A_c`` at some step)."""
    if not flags or any(step is None for step in flags):
        return None
    return np.stack([*flags, flags[-1]], axis=1)


def _frame(base: RiskFlowParallelEnv) -> tuple[np.ndarray, ...]:
    scene, events = base.scene, base.last_events
    flags = (scene.present.copy(), scene.active.copy(), events.centroid_offroad, events.offroad)
    return (scene.current.copy(), *flags)


def _mean_ms(seconds: list[float]) -> float | None:
    return 1e3 * float(np.mean(seconds)) if seconds else None


def _record(base: RiskFlowParallelEnv, frames: list, events: tuple) -> EpisodeRecord:
    """The record of the episode that just ended (metrics but the timings)."""
    arrays = tuple(np.stack(f, axis=1) for f in zip(*frames, strict=True))
    return episode_record(base.view(), arrays, events)


def episode_record(
    view: SceneView, frames: tuple[np.ndarray, ...], events: tuple[dict[str, Any], ...]
) -> EpisodeRecord:
    """An :class:`EpisodeRecord` (metrics but the timings) from what an episode recorded;
    the one place that builds it, for :class:`ClosedLoop` and for batched rollouts
    (``policies.evaluation.batched``).

    Args:
        view: the scene at the episode's end (its sizes and scenario rows).
        frames: ``(states, in_scene, active, offroad_centroid, offroad_footprint)``:
            (A, S + 1, 4) states and (A, S + 1) bool flags (``in_scene`` is the state's
            ``present``) from the reset to the last step.
        events: the episode's event-log rows (``episode_summary`` last).
    """
    states, in_scene, active, centroid, footprint = frames
    scenario = view.scenario
    present = in_scene[:, 0]
    summary = events[-1] if events and events[-1]["event"] == "episode_summary" else {}
    live = active[:, :-1] & in_scene[:, 1:]  # live before each step and still there after
    road = offroad_counts(centroid[:, 1:], footprint[:, 1:], live)  # the env's own flags
    others = present.copy()
    others[0] = False
    length, width = np.asarray(view.length), np.asarray(view.width)
    gap = separation(
        states[:1, :, :2], states[:1, :, YAW], length[:1, None], width[:1, None],
        states[others, :, :2], states[others, :, YAW],
        length[others, None], width[others, None],
    )  # fmt: skip
    gap = gap[in_scene[others]]  # not after a vehicle left
    metrics = {
        "scenario": scenario.name,
        "steps": states.shape[1] - 1,
        "collisions": summary.get("collisions", 0),
        "ego_collided": bool(summary.get("ego_collided", False)),
        "time_to_first_collision": summary.get("time_to_first_collision"),
        "time_to_first_ego_collision": summary.get("time_to_first_ego_collision"),
        "offroad_events": summary.get("offroad_events", 0),
        "ego_offroad": bool(footprint[0].any()),
        "orr_centroid": road.centroid_rate,
        "orr_footprint": road.footprint_rate,
        "min_distance_to_ego": float(gap.min()) if gap.size else None,
    }
    return EpisodeRecord(
        scenario=scenario,
        scenario_rows=np.asarray(view.scenario_rows).copy(),
        agent_names=tuple(view.agent_names),
        states=states,
        in_scene=in_scene,
        active=active,
        offroad_centroid=centroid,
        offroad_footprint=footprint,
        events=events,
        metrics=metrics,
        dt=view.dt,
    )


def planning_metrics(cycle_times: list[float], ego_times: list[float]) -> dict[str, Any]:
    """The timing entries of :data:`METRICS` from the wall times [s] of the planning
    cycles and of the ego planner's calls."""
    return {
        "planning_cycles": len(cycle_times),
        "planning_time_ms": _mean_ms(cycle_times),
        "planning_time_max_ms": 1e3 * max(cycle_times) if cycle_times else None,
        "ego_time_ms": _mean_ms(ego_times),
    }


def summarize(records: list[EpisodeRecord], confidence: float = 0.95) -> dict[str, dict]:
    """Rates (Wilson intervals) and means (bootstrap intervals) over episodes.

    Returns:
        ``{name: {"value", "low", "high", "n"}}`` (None where undefined, e.g. no
        collision to time) for ``ego_collision_rate``,
        ``collision_rate`` (any pair), ``ego_offroad_rate`` (shares of episodes),
        ``time_to_first_ego_collision`` [s] (over the episodes with one),
        ``min_distance_to_ego`` [m], ``orr_centroid``, ``orr_footprint`` and
        ``planning_time_ms`` (means over episodes, bootstrap intervals).
    """
    metrics = [record.metrics for record in records]
    summary: dict[str, dict] = {}
    for name, flag in (
        ("ego_collision_rate", "ego_collided"),
        ("collision_rate", "collisions"),
        ("ego_offroad_rate", "ego_offroad"),
    ):
        summary[name] = rate(sum(bool(m[flag]) for m in metrics), len(metrics), confidence)
    for name in (
        "time_to_first_ego_collision",
        "min_distance_to_ego",
        "orr_centroid",
        "orr_footprint",
        "planning_time_ms",
    ):
        summary[name] = mean_summary([m[name] for m in metrics], confidence)
    return summary
