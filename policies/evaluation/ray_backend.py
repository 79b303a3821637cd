"""``riskflow-eval --backend ray``: the rollouts as Ray tasks, on a local Ray instance or a
cluster.

Each job is one task (``num_cpus=1``, one torch thread, as a local worker process);
the driver keeps at most ``2 x`` the cluster's CPUs of tasks in flight and yields each
result as it arrives, so the caller (:func:`~.runner.run_evaluation`) writes the results
file, fsynced row by row, as with the local backend, and a run of 10,000 scenes never
holds more than a window of them. A rollout is a function of its job only, so the rows
are bit-identical to the local backend's for the same seeds (only their order differs).

Without ``address`` a local Ray starts with ``workers`` CPUs and stops at the end; with
one (``"auto"``, ``"ray://host:10001"``, ...) the tasks go to that cluster, whose nodes
need the same riskflow-env installed (Ray's ``runtime_env`` can ship it). Ray retries a
task whose worker died (``max_retries``), which is safe: a rerun gives the same row.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import numpy as np

from policies.evaluation.options import Job
from policies.evaluation.rollout import run_job

IN_FLIGHT_PER_CPU = 2  # tasks in flight per cluster CPU
MAX_RETRIES = 3  # reruns of a task whose worker process died


def _run_job_one_thread(job: Job) -> tuple[dict, dict[str, np.ndarray]]:
    import torch

    torch.set_num_threads(1)
    return run_job(job)


def ray_results(
    jobs: list[Job], workers: int, address: str | None = None
) -> Iterator[tuple[dict, dict[str, np.ndarray]]]:
    """Run ``jobs`` as Ray tasks; yields ``run_job``'s result per job as it finishes.

    Args:
        jobs: the rollouts.
        workers: CPUs of the local Ray instance (ignored with ``address``).
        address: a Ray cluster to connect to; None starts a local Ray.
    """
    import ray

    started = not ray.is_initialized()
    if started:
        if address is None:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
    try:
        task = ray.remote(num_cpus=1, max_retries=MAX_RETRIES)(_run_job_one_thread)
        window = max(1, IN_FLIGHT_PER_CPU * int(ray.cluster_resources().get("CPU", workers)))
        queue = iter(jobs)
        pending = [task.remote(job) for job in itertools.islice(queue, window)]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
            pending.extend(task.remote(job) for job in itertools.islice(queue, 1))
    finally:
        if started:
            ray.shutdown()
