"""One evaluation rollout: build the policy and the ego, run closed loop, measure.

:func:`run_job` is what a worker process runs for one :class:`~.options.Job`: a fresh
policy (noise seeded from the job's seed and scene only, so a rollout does not depend on
which worker ran it or on what it ran before), a fresh ego planner, one
:class:`~policies.harness.ClosedLoop` episode, then the metrics of
:mod:`riskflow_env.metrics` on the episode's :class:`RolloutRecord` and the failure
analysis of its ego collisions (:mod:`policies.stress.failures`: type, avoidability,
attacker plausibility; the row's ``failures``). The ego is the
planner under test, so the realism metrics (ORR, ADE/FDE, KDD, WOSAC) score the other
vehicles only; SCR counts every pair, the ego included.
"""

from __future__ import annotations

import functools
import math
import time
from typing import Any

import numpy as np
import torch

from policies import harness
from policies.evaluation.options import Job, method_label, open_data
from policies.harness import ClosedLoop, EpisodeRecord
from policies.learned.checkpoint import checkpoint_digest
from policies.planners import make_planner
from policies.registry import build_policy
from policies.stress.failures import analyse
from policies.stress.summary import episode_outcome
from riskflow_env.config import EnvConfig
from riskflow_env.metrics import RolloutRecord, kinematic_samples, rollout_metrics, wosac_scene
from riskflow_env.scenarios import Scenario, ScenarioBank
from riskflow_env.scenarios.scenarionet_dataset import ScenarioNetDataset
from riskflow_env.view import ScenePolicy

HISTORY = 2  # logged steps prepended as context (WOSAC's central differences)
_WARM: set[tuple] = set()  # (label, k, interval) this process has warmed up


@functools.cache
def _scenes(data: str) -> ScenarioBank | ScenarioNetDataset:
    return open_data(data)


def job_scenario(job: Job) -> Scenario:
    """The job's scene (the source is opened once per process; a ScenarioNet scene is
    read when a job needs it)."""
    scene = _scenes(job.run.data)[job.scene_index]
    if scene.name != job.scene:
        raise RuntimeError(f"scene {job.scene_index} of {job.run.data} is {scene.name!r}, "
                           f"expected {job.scene!r}: the scenario directory changed")  # fmt: skip
    return scene


def json_number(value: Any) -> Any:
    """A JSON-ready number: numpy scalars to Python, NaN / inf to None."""
    if value is None or isinstance(value, (bool, np.bool_)):
        return None if value is None else bool(value)
    value = float(value)
    return value if math.isfinite(value) else None


def job_policy(job: Job) -> ScenePolicy:
    """A fresh scene policy of the job's method, options, K and interval, its noise seeded
    with the job's ``policy_seed``; ValueError when its ``checkpoint`` file no longer holds
    the weights the run recorded (``Job.checkpoint_sha256``: retrained during the run)."""
    if job.checkpoint_sha256 is not None:
        path = job.options["checkpoint"]
        if checkpoint_digest(path) != job.checkpoint_sha256:
            raise ValueError(
                f"checkpoint {path} changed during the run (weights_sha256 "
                f"{job.checkpoint_sha256[:12]} when it started); evaluate it into another --out"
            )
    return build_policy(
        job.method, job.options, k=job.k, planning_interval=job.interval,
        target=job.run.target, seed=job.policy_seed, device=job.run.device,
    )  # fmt: skip


def warm_up(job: Job, scenario: Scenario, config: EnvConfig) -> float:
    """First rollout of a method (and K, interval) in this process: one untimed env step
    with a throwaway policy, so that one-off costs (first model call, allocator) stay out
    of the timings. The rollout's own policy is untouched: its numbers do not depend on it."""
    label = (method_label(job.method, job.options), job.k, job.interval)
    if label in _WARM:
        return 0.0
    start = time.perf_counter()
    harness.warm_up(make_planner(job.run.ego), job_policy(job), scenario, config, job.seed)
    _WARM.add(label)
    return time.perf_counter() - start


def rollout_episode(job: Job) -> tuple[EpisodeRecord, RolloutRecord, dict[str, float]]:
    """Run one job's closed-loop episode (no metrics).

    Returns:
        ``(episode, record, timing)``: the harness's episode, its :class:`RolloutRecord`
        (``HISTORY`` logged steps of context; the ego is not evaluated) and
        ``{"rollout_s", "setup_s", "warmup_s"}``.
    """
    scenario = job_scenario(job)
    run = job.run
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        start = time.perf_counter()
        policy = job_policy(job)
        planner = make_planner(run.ego)
        setup = time.perf_counter() - start
        config = run.env_config(scenario.dt)
        warmup = warm_up(job, scenario, config)
        with ClosedLoop(planner, policy, config=config, scenarios=scenario) as loop:
            start = time.perf_counter()
            episode = loop.run(scenario, seed=job.seed)
            wall = time.perf_counter() - start
    finally:
        torch.set_num_threads(threads)
    record = rollout_record(scenario, episode)
    return episode, record, {"rollout_s": wall, "setup_s": setup, "warmup_s": warmup}


def run_job(job: Job) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Run one rollout.

    Returns:
        ``(row, samples)``: the results row (module ``results`` documents it) and the
        rollout's KDD samples (``KinematicSamples.as_arrays()``).
    """
    return score(job, *rollout_episode(job))


def rollout_record(scenario: Scenario, episode: EpisodeRecord) -> RolloutRecord:
    """The :class:`RolloutRecord` of an episode: ``HISTORY`` logged steps of context,
    every present vehicle but the ego (slot 0) evaluated."""
    others = episode.present.copy()
    others[0] = False  # slot 0 is the ego
    return RolloutRecord.from_scenario(
        scenario, episode.states, episode.in_scene, episode.scenario_rows,
        history=HISTORY, evaluated=others,
    )  # fmt: skip


def score(
    job: Job, episode: EpisodeRecord, record: RolloutRecord, timing: dict[str, float]
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The results row and KDD samples of one finished rollout (:func:`run_job`'s
    result; the batched path, :mod:`~.batched`, scores its episodes here too).

    Args:
        job: the rollout's job.
        episode: its episode (``metrics`` with the harness's timing entries).
        record: :func:`rollout_record` of the episode.
        timing: ``{"rollout_s", "setup_s", "warmup_s"}`` [s].
    """
    run = job.run
    others = record.evaluated
    start = time.perf_counter()
    metrics = {key: json_number(v) for key, v in rollout_metrics(record).items()}
    wosac = None
    if run.wosac:
        wosac = {key: json_number(v) for key, v in wosac_scene([record]).items()}
    samples = kinematic_samples(record).as_arrays()
    failures = episode_outcome(episode, analyse(episode))["failures"]
    scored = time.perf_counter() - start

    m = episode.metrics
    cycles = m["planning_cycles"]
    row = {
        "key": job.key,
        "method": job.method,
        "label": method_label(job.method, job.options),
        "options": job.options,
        "k": job.k,
        "interval": job.interval,
        "scene": job.scene,
        "scene_index": job.scene_index,
        "seed": job.seed,
        "policy_seed": job.policy_seed,
        "steps": m["steps"],
        "agents": int(others.sum()),
        **metrics,
        "harness": {
            "ego_collided": bool(m["ego_collided"]),
            "collision_events": m["collisions"],
            "time_to_first_collision": json_number(m["time_to_first_collision"]),
            "time_to_first_ego_collision": json_number(m["time_to_first_ego_collision"]),
            "min_distance_to_ego": json_number(m["min_distance_to_ego"]),
            "ego_offroad": bool(m["ego_offroad"]),
        },
        "failures": failures,
        "wosac": wosac,
        "timing": {
            **timing,
            "metrics_s": scored,
            "planning_cycles": cycles,
            "planning_s": (m["planning_time_ms"] or 0.0) * cycles / 1e3,
            "cycle_ms_mean": json_number(m["planning_time_ms"]),
            "cycle_ms_max": json_number(m["planning_time_max_ms"]),
            "ego_ms_mean": json_number(m["ego_time_ms"]),
        },
    }
    return row, samples
