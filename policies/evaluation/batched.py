"""``riskflow-eval --batch-scenes N``: up to N rollouts of one method stepped as one batch.

:func:`group_jobs` cuts the rollouts to run into groups of at most N consecutive jobs that
share the method, its options, K, the planning interval and the run settings (scenes and
seeds differ within a group; the order is :func:`~.options.plan_jobs`'s). :func:`run_batch`
rolls one group out:

* the group's scenes in one :class:`~riskflow_env.scene_batch.SceneBatch`: one
  :func:`riskflow_env.simulator.transition` per step for every scene and agent, each scene
  on its own map;
* the traffic of every scene from one policy of the method
  (:func:`~policies.rl.vector_traffic.batched_traffic`): a learned adversary (RiskFlow and
  its ablations, the unguided generator, STRIVE-style, the diffusion baselines) becomes a
  :class:`~policies.pipeline.batched.BatchedAdversary` that plans every scene due
  to re-plan in one call (RiskFlow and the unguided generator: one encoder pass, one
  generator pass, one guidance loop; STRIVE-style one latent optimisation over all the
  scenes' rows; the diffusion baselines one base chain and one guided chain for all the
  scenes), each scene with its job's noise seed (``policy_seed``); a
  rule-based policy (IDM, replay, constant velocity) is asked scene by scene;
* the ego planner, one per scene, called scene by scene (a Python loop over the scenes:
  the planners under test have no batched form);
* one event recorder per scene (the harness's :class:`~riskflow_env.wrappers.event_log.
  EventRecorder`). Each scene ends on its own (at an ego collision with
  ``--stop-at-ego-collision``); a scene that has ended is neither planned, asked nor
  recorded while the others go on.

Each episode becomes the harness's :class:`~policies.harness.EpisodeRecord`
(:func:`~policies.harness.episode_record`) and is scored by :func:`~.rollout.score`, as on
the per-scene path: a row matches the per-scene path's row of the same job to float
rounding (the network's outputs are those of the scene alone, bit for bit; the guidance's
Adam steps amplify the last bits of a few batch-shaped ops), and the same jobs give the
same rows, bit for bit.

Timings: the group's wall times (``rollout_s``, ``setup_s``, ``warmup_s``) are shared
equally by its rollouts and each planning call's by the scenes it planned (``planning_s``,
``cycle_ms_mean``, ``cycle_ms_max``), so the sum over a run's rows is its wall time, as on
the per-scene path; ``ego_ms_mean`` is the scene's own.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from policies.evaluation.options import Job
from policies.evaluation.rollout import job_policy, job_scenario, rollout_record, score, warm_up
from policies.harness import (
    EGO,
    EpisodeRecord,
    controllable_now,
    episode_record,
    guided_frames,
    planning_metrics,
)
from policies.pipeline.batched import BatchedAdversary
from policies.planners import make_planner
from policies.planners.base import EgoPlanner, as_action, reset_planner
from policies.rl.vector_traffic import SceneLoop, batched_traffic
from riskflow_env.config import EnvConfig, is_integer
from riskflow_env.events import FrameEvents
from riskflow_env.scenarios import Scenario
from riskflow_env.scene_batch import SceneBatch
from riskflow_env.wrappers.event_log import EventRecorder


def _group_key(job: Job) -> tuple:
    return (job.method, job.options, job.k, job.interval, job.run)


def group_jobs(jobs: Sequence[Job], size: int) -> list[list[Job]]:
    """``jobs`` in groups of at most ``size`` consecutive jobs of one method, options, K,
    interval and run settings (module docstring)."""
    if not is_integer(size) or size < 1:
        raise ValueError(f"--batch-scenes must be an int >= 1, got {size!r}")
    groups: list[list[Job]] = []
    for job in jobs:
        last = groups[-1] if groups else None
        if last is not None and len(last) < size and _group_key(last[0]) == _group_key(job):
            last.append(job)
        else:
            groups.append([job])
    return groups


def run_batch(jobs: Sequence[Job]) -> list[tuple[dict[str, Any], dict[str, np.ndarray]]]:
    """Roll out one group of :func:`group_jobs` together; ``run_job``'s ``(row, samples)``
    of each job, in the group's order."""
    jobs = list(jobs)
    episodes, timing = rollout_batch(jobs)
    return [
        score(job, episode, rollout_record(episode.scenario, episode), timing)
        for job, episode in zip(jobs, episodes, strict=True)
    ]


def rollout_batch(jobs: Sequence[Job]) -> tuple[list[EpisodeRecord], dict[str, float]]:
    """Run the closed-loop episodes of one group of jobs (no metrics).

    Returns:
        ``(episodes, timing)``: one :class:`EpisodeRecord` per job (``metrics`` with the
        timing entries, module docstring) and each rollout's share of the group's
        ``{"rollout_s", "setup_s", "warmup_s"}`` [s].
    """
    jobs = list(jobs)
    if not jobs or any(_group_key(job) != _group_key(jobs[0]) for job in jobs):
        raise ValueError("jobs must be a non-empty group of group_jobs (one method, K, ...)")
    first, count = jobs[0], len(jobs)
    scenarios = [job_scenario(job) for job in jobs]
    if len({scenario.dt for scenario in scenarios}) > 1:
        raise ValueError("the scenes of one batch must share their time step dt")
    config = first.run.env_config(scenarios[0].dt)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        start = time.perf_counter()
        traffic = batched_traffic(job_policy(first), count, config)
        planners = [make_planner(first.run.ego) for _ in jobs]
        setup = time.perf_counter() - start
        warmup = warm_up(first, scenarios[0], config)
        start = time.perf_counter()
        episodes = _run(jobs, scenarios, config, traffic, planners)
        wall = time.perf_counter() - start
    finally:
        torch.set_num_threads(threads)
    timing = {"rollout_s": wall, "setup_s": setup, "warmup_s": warmup}
    return episodes, {key: seconds / count for key, seconds in timing.items()}


def _run(
    jobs: list[Job],
    scenarios: list[Scenario],
    config: EnvConfig,
    traffic: BatchedAdversary | SceneLoop,
    planners: list[EgoPlanner],
) -> list[EpisodeRecord]:
    """The closed loop of ``harness.ClosedLoop.run`` over a batch of scenes."""
    count = len(jobs)
    batch = SceneBatch(count, config, scenarios)
    observations, _ = batch.reset(
        [job.seed for job in jobs], [{"scenario": scenario} for scenario in scenarios]
    )
    views = batch.views()
    recorders = [EventRecorder() for _ in jobs]
    for index, (job, view) in enumerate(zip(jobs, views, strict=True)):
        reset_planner(planners[index], view)
        traffic.reset_scene(index, view, job.policy_seed)
        recorders[index].begin(view.scenario.name)
        recorders[index].observe(view, batch.envs[index].last_events)
    ego_obs = np.stack([rows[EGO] for rows in observations])
    initial = [env.last_events for env in batch.envs]  # the events at the reset
    frames = [
        _frame(
            batch,
            np.stack([events.centroid_offroad for events in initial]),
            np.stack([events.offroad for events in initial]),
        )
    ]
    final_views = list(views)
    steps = np.zeros(count, dtype=np.int64)
    cycle_times: list[list[float]] = [[] for _ in jobs]
    ego_times: list[list[float]] = [[] for _ in jobs]
    guided: list[list[np.ndarray | None]] = [[] for _ in jobs]
    running = batch.state.active.any(axis=1)
    while running.any():
        start = time.perf_counter()
        actions = traffic.act_array(views, running)
        elapsed = time.perf_counter() - start
        if isinstance(traffic, BatchedAdversary):
            planned = list(traffic.last_planned)
        else:  # a reactive policy: every call is a cycle (as in the harness)
            planned = np.flatnonzero(running).tolist()
        for index in planned:
            cycle_times[index].append(elapsed / len(planned))
        for index in np.flatnonzero(running):
            guided[index].append(controllable_now(traffic.scenes[index], views[index].num_agents))
        for index in np.flatnonzero(running & batch.state.active[:, 0]):
            start = time.perf_counter()
            action = as_action(planners[index](ego_obs[index], views[index]), "the ego planner")
            ego_times[index].append(time.perf_counter() - start)
            if not np.isfinite(action).all():
                raise ValueError(f"the ego planner returned a NaN/inf action {action.tolist()}")
            actions[index, 0] = action
        transition = batch.step(actions)
        views = batch.views()
        ego_obs = transition.observations[:, 0]
        events = transition.events
        frames.append(_frame(batch, events.centroid_offroad, events.offroad))
        steps += running
        ended = running & ~batch.state.active.any(axis=1)
        for index in np.flatnonzero(running):
            recorders[index].observe(views[index], _scene_events(events, index))
        for index in np.flatnonzero(ended):
            recorders[index].finish("done")
            final_views[index] = views[index]
        running &= ~ended
    stacked = (np.stack(f, axis=2) for f in zip(*frames, strict=True))
    states, in_scene, active, centroid, footprint = stacked
    episodes = []
    for index in range(count):
        last = steps[index] + 1
        scene_frames = (
            states[index, :, :last],
            in_scene[index, :, :last],
            active[index, :, :last],
            centroid[index, :, :last],
            footprint[index, :, :last],
        )
        record = episode_record(final_views[index], scene_frames, tuple(recorders[index].events))
        record.metrics.update(planning_metrics(cycle_times[index], ego_times[index]))
        episodes.append(dataclasses.replace(record, guided=guided_frames(guided[index])))
    return episodes


def _frame(
    batch: SceneBatch, centroid: np.ndarray, footprint: np.ndarray
) -> tuple[np.ndarray, ...]:
    """(N, A, 4) states, (N, A) in-scene and active flags of every scene now, and the
    (N, A) off-road flags (centroid, footprint) given."""
    state = batch.state
    return state.current.copy(), state.present.copy(), state.active.copy(), centroid, footprint


def _scene_events(events: FrameEvents, index: int) -> FrameEvents:
    """Scene ``index``'s events of a batch's ``events``."""
    return FrameEvents(
        collisions=events.collisions[index],
        offroad_fraction=events.offroad_fraction[index],
        sdf_depth=events.sdf_depth[index],
        centroid_offroad=events.centroid_offroad[index],
    )


__all__ = ["group_jobs", "rollout_batch", "run_batch"]
