"""Evaluation metrics (docs/reference/metrics.md): pure numpy functions over rollout records.

A :class:`RolloutRecord` holds one rollout's simulated tracks, its logged reference,
masks, sizes, the map and the ego slot (``RolloutRecord.from_scenario`` builds one from
an env episode). Definitions with formulas: ``docs/reference/metrics.md``.

==============  =======================================  ==============================
metric          per rollout                              over rollouts
==============  =======================================  ==============================
SCR, ego rate   :func:`collisions`                       :func:`collision_rates`
ORR             :func:`offroad` (centroid, footprint)    :func:`offroad_rates`
                (:func:`offroad_counts` from flags)
ADE, FDE        :func:`displacement_errors`              :func:`displacement_means`
still drift     :func:`standstill_drift` (log-parked)    --
progress,       :func:`progress` (log-movers, parked     pooled in
stalls          cars turned in place, map's edge)        :func:`aggregate_rollout_metrics`
KDD             :func:`kinematic_samples`                :func:`kdd`
CS, RS          --                                       :func:`safety_realism_scores`
WOSAC realism   --                                       :func:`wosac_scene` (N rollouts
                                                         of a scene), :func:`wosac_aggregate`
==============  =======================================  ==============================

:func:`rollout_metrics` / :func:`aggregate_rollout_metrics` / :func:`method_metrics`
carry SCR, ORR, ADE, FDE and progress through flat per-rollout rows (for a results file).
"""

from __future__ import annotations

from riskflow_env.metrics.displacement import (
    DisplacementResult,
    displacement_errors,
    displacement_means,
    standstill_drift,
)
from riskflow_env.metrics.kinematics import (
    KINEMATIC_FEATURES,
    KinematicSamples,
    jerk_steps,
    kdd,
    kdd_over_records,
    kinematic_samples,
)
from riskflow_env.metrics.progress import ProgressResult, progress
from riskflow_env.metrics.rollout import NO_EGO, RolloutRecord
from riskflow_env.metrics.safety import (
    CollisionResult,
    OffroadResult,
    collision_involvement,
    collision_rates,
    collisions,
    offroad,
    offroad_counts,
    offroad_rates,
)
from riskflow_env.metrics.scores import min_max_normalise, safety_realism_scores
from riskflow_env.metrics.summary import (
    ROLLOUT_KEYS,
    aggregate_rollout_metrics,
    method_metrics,
    rollout_metrics,
)
from riskflow_env.metrics.wosac import WOSAC_2024, FeatureConfig, wosac_aggregate, wosac_scene

__all__ = [
    "KINEMATIC_FEATURES",
    "NO_EGO",
    "ROLLOUT_KEYS",
    "WOSAC_2024",
    "CollisionResult",
    "DisplacementResult",
    "FeatureConfig",
    "KinematicSamples",
    "OffroadResult",
    "ProgressResult",
    "RolloutRecord",
    "aggregate_rollout_metrics",
    "collision_involvement",
    "collision_rates",
    "collisions",
    "displacement_errors",
    "displacement_means",
    "jerk_steps",
    "kdd",
    "kdd_over_records",
    "kinematic_samples",
    "method_metrics",
    "min_max_normalise",
    "offroad",
    "offroad_counts",
    "offroad_rates",
    "progress",
    "rollout_metrics",
    "standstill_drift",
    "safety_realism_scores",
    "wosac_aggregate",
    "wosac_scene",
]
