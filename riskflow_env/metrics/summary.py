"""Per-rollout metric rows and their aggregation over many rollouts.

:func:`rollout_metrics` turns one :class:`RolloutRecord` into a flat dict of numbers
(JSON-ready: a results file can take one line per rollout as soon as the rollout
ends); :func:`aggregate_rollout_metrics` combines such rows into one method's SCR,
ORR, ADE and FDE exactly as the functions over records would (rates pool their counts,
ADE / FDE pool their agents). KDD is a distance between distributions and cannot be
rebuilt from per-rollout numbers: keep each rollout's
:func:`~riskflow_env.metrics.kinematics.kinematic_samples` (``as_arrays`` for
``np.savez``) and pass them to :func:`method_metrics`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from riskflow_env.metrics.displacement import displacement_errors
from riskflow_env.metrics.kinematics import KinematicSamples, kdd
from riskflow_env.metrics.progress import progress
from riskflow_env.metrics.rollout import RolloutRecord
from riskflow_env.metrics.safety import OffroadResult, collisions, offroad

ROLLOUT_KEYS = (
    "collision",  # 1.0 if any agent-agent collision, else 0.0
    "ego_collision",  # 1.0 if a collision involves the ego
    "first_collision_step",  # first scored step with a collision, -1 if none
    "first_ego_collision_step",  # first scored step with a collision of the ego, -1 if none
    "offroad_centroid_steps",  # agent-steps with the centre off the road
    "offroad_footprint_steps",  # agent-steps with a footprint point off the road
    "agent_steps",  # scored agent-steps (ORR's denominator)
    "ade",  # mean ADE over the rollout's agents [m] (NaN if none)
    "fde",  # mean FDE over the rollout's agents [m] (NaN if none)
    "displacement_agents",  # agents with an ADE / FDE
    "movers",  # vehicles that move in the log (progress, riskflow_env.metrics.progress)
    "stalled",  # of them, those with progress below STALL_PROGRESS
    "driven_m",  # path the simulation drives, summed over the movers [m]
    "logged_m",  # path the log drives on the same steps, summed over the movers [m]
    "parked",  # vehicles that stand still in the log
    "turned_in_place",  # of them, those the simulation turns in place
    "edge_steps",  # simulated vehicle-steps near the border of the map
    "edge_hard_steps",  # of them, those over HARD_ACCELERATION
    "log_edge_steps",  # the same two counts of the log
    "log_edge_hard_steps",
)


def rollout_metrics(record: RolloutRecord, tolerance: float = 0.0) -> dict[str, float]:
    """The ``ROLLOUT_KEYS`` numbers of one rollout (ORR counts need the record's map;
    without one they are 0 and ``agent_steps`` is 0).

    Args:
        record: the rollout.
        tolerance: collision threshold [m] on the SAT separation (0: touching counts).
    """
    hit = collisions(record, tolerance)
    if record.drivable_map is not None:
        road = offroad(record)
        centroid, footprint, steps = road.centroid_steps, road.footprint_steps, road.agent_steps
    else:
        centroid = footprint = steps = 0
    errors = displacement_errors(record)
    moving = progress(record)
    return {
        "collision": float(hit.collided),
        "ego_collision": float(hit.ego_collided),
        "first_collision_step": float(hit.first_step),
        "first_ego_collision_step": float(hit.first_ego_step),
        "offroad_centroid_steps": float(centroid),
        "offroad_footprint_steps": float(footprint),
        "agent_steps": float(steps),
        "ade": errors.mean_ade,
        "fde": errors.mean_fde,
        "displacement_agents": float(errors.num_agents),
        "movers": float(moving.mover.sum()),
        "stalled": float(moving.stalled.sum()),
        "driven_m": float(moving.driven[moving.mover].sum()),
        "logged_m": float(moving.logged[moving.mover].sum()),
        "parked": float(moving.parked.sum()),
        "turned_in_place": float(moving.turned.sum()),
        "edge_steps": float(moving.edge_steps[0]),
        "edge_hard_steps": float(moving.edge_hard[0]),
        "log_edge_steps": float(moving.edge_steps[1]),
        "log_edge_hard_steps": float(moving.edge_hard[1]),
    }


def aggregate_rollout_metrics(rows: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """One method's metrics from its per-rollout rows.

    Returns:
        ``scr`` and ``ego_collision_rate`` (shares of rollouts), ``orr`` (centroid) and
        ``orr_footprint`` (pooled agent-steps), ``ade`` and ``fde`` [m] (pooled agents),
        ``progress`` (path driven over path logged, pooled over the log-movers),
        ``stalled_share`` (of the log-movers), ``turned_share`` (of the log-parked),
        ``edge_hard_share`` and ``log_edge_hard_share`` (of the vehicle-steps near the
        map's border, simulated and logged), ``num_rollouts``. NaN where nothing is
        counted (or where a row predates a key).
    """
    nan = float("nan")
    count = len(rows)

    def total(key: str) -> float:
        return sum(float(row.get(key, nan)) for row in rows)

    steps, agents = total("agent_steps"), total("displacement_agents")
    road = OffroadResult(  # pooled agent-steps (the counts are whole numbers)
        centroid_steps=int(total("offroad_centroid_steps")),
        footprint_steps=int(total("offroad_footprint_steps")),
        agent_steps=int(steps),
    )

    def pooled_mean(key: str) -> float:  # per-rollout agent means, weighted by agents
        weighted = sum(
            float(row[key]) * float(row["displacement_agents"])
            for row in rows
            if float(row["displacement_agents"]) > 0 and not math.isnan(float(row[key]))
        )
        return weighted / agents if agents else nan

    def share(part: str, whole: str) -> float:
        return total(part) / total(whole) if total(whole) else nan

    return {
        "scr": total("collision") / count if count else nan,
        "ego_collision_rate": total("ego_collision") / count if count else nan,
        "orr": road.centroid_rate,
        "orr_footprint": road.footprint_rate,
        "ade": pooled_mean("ade"),
        "fde": pooled_mean("fde"),
        "progress": share("driven_m", "logged_m"),
        "stalled_share": share("stalled", "movers"),
        "turned_share": share("turned_in_place", "parked"),
        "edge_hard_share": share("edge_hard_steps", "edge_steps"),
        "log_edge_hard_share": share("log_edge_hard_steps", "log_edge_steps"),
        "num_rollouts": float(count),
    }


def method_metrics(
    rows: Sequence[Mapping[str, float]], samples: Sequence[KinematicSamples]
) -> dict[str, float]:
    """:func:`aggregate_rollout_metrics` plus KDD (per feature and ``kdd``) from the
    rollouts' kinematic samples: one row of the CS / RS table
    (:func:`~riskflow_env.metrics.scores.safety_realism_scores`)."""
    return {**aggregate_rollout_metrics(rows), **kdd(samples)}
