"""Closed-loop evaluation harness: ``riskflow-eval`` (docs/tutorials/reproduce.md,
docs/reference/metrics.md).

==================  ==============================================================
module              concept
==================  ==============================================================
``options``         the typed options and the grid of rollouts (jobs, row keys)
``rollout``         one rollout: policy + ego, closed loop, metrics, timing
``results``         the results folder: config check, fsynced rows, KDD samples
``batched``         ``--batch-scenes N``: N rollouts of one method stepped as one batch
``runner``          skip finished rollouts, run the rest in worker processes
``table``           one (K, interval) comparison: what the report prints and plots
``report``          tables per (K, interval): raw metrics, CS / RS, timing
``plots``           CS vs RS, realism vs horizon, speed (PNG)
``cli``             the ``riskflow-eval`` command line
==================  ==============================================================

The methods it compares are those of :mod:`policies.registry` (one name per scene policy).
"""

from __future__ import annotations

from policies.evaluation.options import EvalOptions, Job, plan_jobs
from policies.evaluation.report import build_tables, write_report
from policies.evaluation.results import ConfigMismatch, ResultsLocked, ResultsStore
from policies.evaluation.runner import prepare, run_evaluation
from policies.registry import METHODS, MethodSpec, build_policy

__all__ = [
    "METHODS",
    "ConfigMismatch",
    "EvalOptions",
    "Job",
    "MethodSpec",
    "ResultsLocked",
    "ResultsStore",
    "build_policy",
    "build_tables",
    "plan_jobs",
    "prepare",
    "run_evaluation",
    "write_report",
]
