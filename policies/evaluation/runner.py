"""Run the rollouts of an evaluation: skip the finished ones, farm out the rest.

:func:`run_evaluation` plans the jobs (:func:`~.options.plan_jobs`), checks every method
once in this process (its options build a policy, its plan horizon covers the planning
intervals), drops the jobs whose rows are already in the results file, and runs the rest
in ``workers`` processes (spawned, one torch thread each), in this process, or as Ray
tasks (``--backend ray``, :mod:`~.ray_backend`), with a progress bar; with
``--batch-scenes N`` (local backend) in groups of up to N rollouts stepped as one batch
(:mod:`~.batched`), each group's rows written when the group ends. The parent alone
writes the results file, each row as soon as its rollout (or its batch) returns. Every
rollout is a function of its job only, so the worker count and the backend change the
order of the rows, never their numbers; ``--batch-scenes`` changes them within float
rounding (:mod:`~.batched`).
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from policies.evaluation.batched import group_jobs, run_batch
from policies.evaluation.options import EvalOptions, Job, RunConfig, plan_jobs, scene_names
from policies.evaluation.results import ResultsStore
from policies.evaluation.rollout import run_job
from policies.learned.checkpoint import checkpoint_digest
from policies.registry import build_policy
from riskflow_env.config import DynamicsConfig
from riskflow_env.processes import pool_worker


def check_methods(jobs: list[Job], dt: float = DynamicsConfig().dt) -> None:
    """Build each (method, options) once; ValueError naming the argument when its options
    are rejected or a planning interval exceeds its plan horizon."""
    seen: dict[str, Job] = {}
    intervals: dict[str, set[float]] = {}
    for job in jobs:
        seen.setdefault(job.method, job)
        if job.interval is not None:
            intervals.setdefault(job.method, set()).add(job.interval)
    for method, job in seen.items():
        try:
            policy = build_policy(
                method, job.options, k=job.k, planning_interval=job.interval,
                target=job.run.target, seed=0, device=job.run.device,
            )  # fmt: skip
        except (OSError, TypeError, ValueError) as err:  # OSError: a checkpoint not found
            given = ", ".join(f"{k}={v!r}" for k, v in job.options.items()) or "defaults"
            raise ValueError(f"--methods {method} (options: {given}): {err}") from err
        horizon = getattr(policy, "horizon", None)
        for interval in sorted(intervals.get(method, ())):
            if horizon is not None and interval > horizon * dt + 1e-9:
                raise ValueError(
                    f"--interval: {interval} s exceeds the plan horizon of {method} "
                    f"({horizon} steps = {horizon * dt:.1f} s)"
                )


def checkpoint_digests(jobs: list[Job]) -> dict[str, str]:
    """``weights_sha256`` of each ``checkpoint`` option of the jobs' methods, keyed by the
    path as given (:meth:`~.results.ResultsStore.check_config`); read after
    :func:`check_methods`, so every file is known to load."""
    paths = {str(job.options["checkpoint"]) for job in jobs if job.options.get("checkpoint")}
    return {path: checkpoint_digest(path) for path in sorted(paths)}


def _init_worker() -> None:
    torch.set_num_threads(1)
    pool_worker()  # a killed riskflow-eval leaves no worker behind; Ctrl-C is the parent's


def _results(jobs: list[Job], options: EvalOptions) -> Iterator[tuple[dict, dict[str, np.ndarray]]]:
    workers = options.workers
    if options.backend == "ray":
        from policies.evaluation.ray_backend import ray_results

        yield from ray_results(jobs, workers, options.address)
        return
    if options.batch_scenes > 1:
        yield from _batched_results(jobs, options)
        return
    if workers <= 1:
        for job in jobs:
            yield run_job(job)
        return
    context = multiprocessing.get_context("spawn")
    with context.Pool(workers, initializer=_init_worker) as pool:
        yield from pool.imap_unordered(run_job, jobs, chunksize=1)


def _batched_results(
    jobs: list[Job], options: EvalOptions
) -> Iterator[tuple[dict, dict[str, np.ndarray]]]:
    """``--batch-scenes N``: the jobs in groups of N (:func:`~.batched.group_jobs`), each
    group's rows yielded when the group ends."""
    groups = group_jobs(jobs, options.batch_scenes)
    if options.workers <= 1:
        for group in groups:
            yield from run_batch(group)
        return
    context = multiprocessing.get_context("spawn")
    with context.Pool(options.workers, initializer=_init_worker) as pool:
        for rows in pool.imap_unordered(run_batch, groups, chunksize=1):
            yield from rows


def prepare(options: EvalOptions) -> tuple[ResultsStore, list[Job]]:
    """Check the options (ValueError naming the argument) and the results folder's
    configuration (:class:`~.results.ConfigMismatch`) and take its writer lock
    (:class:`~.results.ResultsLocked` if another run holds it); returns the store (locked
    until :func:`run_evaluation` ends) and every job."""
    store = ResultsStore(options.out)
    jobs = plan_jobs(options, scene_names(options.data, options.scenes))
    check_methods(jobs)
    digests = checkpoint_digests(jobs)
    jobs = [
        replace(job, checkpoint_sha256=digests[str(job.options["checkpoint"])])
        if job.options.get("checkpoint")
        else job
        for job in jobs
    ]
    try:
        # takes the folder's writer lock
        store.check_config(RunConfig.from_options(options).as_json(), digests)
    except OSError as err:  # e.g. the folder cannot be created
        store.unlock()
        raise ValueError(f"--out: {err}") from err
    except BaseException:
        store.unlock()
        raise
    return store, jobs


def run_evaluation(
    options: EvalOptions,
    progress: bool = True,
    prepared: tuple[ResultsStore, list[Job]] | None = None,
) -> dict[str, Any]:
    """Run every missing rollout of ``options`` into ``options.out``.

    Args:
        options: the evaluation.
        progress: show a progress bar.
        prepared: :func:`prepare`'s result, if already called.

    Returns:
        ``{"planned", "skipped", "ran", "wall_s"}``: rollouts asked for, already present,
        run now, and the wall time [s].
    """
    store, jobs = prepared or prepare(options)
    done = store.done_keys()
    todo = [job for job in jobs if job.key not in done]
    start = time.perf_counter()
    bar = tqdm(total=len(todo), desc="rollouts", unit="rollout", disable=not progress)
    if len(todo) < len(jobs):
        bar.write(f"{len(jobs) - len(todo)} of {len(jobs)} rollouts already in {store.results}")
    try:
        for row, samples in _results(todo, options):
            store.append(row, samples)
            bar.set_postfix_str(f"{row['label']} {row['scene']}", refresh=False)
            bar.update()
    finally:
        bar.close()
        store.unlock()
    return {
        "planned": len(jobs),
        "skipped": len(jobs) - len(todo),
        "ran": len(todo),
        "wall_s": time.perf_counter() - start,
    }
