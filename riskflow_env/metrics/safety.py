"""Safety metrics: SCR (collision rate over rollouts) and ORR (off-road rate).

SCR: a rollout *collides* when two valid vehicles' boxes overlap at any scored step
(:func:`riskflow_env.geometry.pairwise_overlap`, the env's own collision test, touching
counts). SCR is the share of rollouts that collide; the ego-involved rate is the share
whose collisions include the ego. All valid agents count, evaluated or not.

ORR, over the agent-steps of evaluated agents (valid, scored step):

* centroid (paper style): share whose box centre is off the drivable area,
  ``sdf(centre) > 0``;
* footprint: share with any of the 9 footprint points
  (:func:`riskflow_env.geometry.footprint_points`) off the drivable area, as the env's
  off-road event.

Rates over many rollouts pool the agent-steps (sum of off-road steps / sum of steps).

:func:`offroad_counts` is the one place that counts off-road agent-steps; its ``counted``
mask says which agent-steps make the denominator, the only thing in which the two
users differ:

* :func:`offroad` (the evaluation's ORR): the record's scored agent-steps (evaluated
  agent, valid, scored step), flags from the record's states and map;
* the closed-loop harness (``policies.harness``, ``orr_centroid`` / ``orr_footprint``):
  the live agent-steps of an env episode (every vehicle, the ego included, while it is
  still controlled; done vehicles standing as obstacles do not count), flags from the
  env's own per-step events (:func:`riskflow_env.events.detect`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from riskflow_env.dynamics import YAW
from riskflow_env.geometry import CENTRE, footprint_points, pairwise_overlap
from riskflow_env.maps import DrivableMap
from riskflow_env.metrics.rollout import NO_EGO, RolloutRecord


@dataclass(frozen=True)
class CollisionResult:
    """Collisions of one rollout.

    Attributes:
        collided: at least one agent-agent overlap at a scored step.
        ego_collided: at least one of them involves the ego.
        first_step: first scored step with an overlap, -1 if none.
        first_ego_step: first scored step with an overlap of the ego, -1 if none.
        pairs: (A, A) bool, symmetric: the pair overlapped at some scored step.
    """

    collided: bool
    ego_collided: bool
    first_step: int
    pairs: np.ndarray
    first_ego_step: int = -1


@dataclass(frozen=True)
class OffroadResult:
    """Off-road agent-step counts of one rollout (or pooled over many).

    Attributes:
        centroid_steps: agent-steps whose centre is off the drivable area.
        footprint_steps: agent-steps with any footprint point off the drivable area.
        agent_steps: scored agent-steps (evaluated agent, valid, scored step).
    """

    centroid_steps: int
    footprint_steps: int
    agent_steps: int

    @property
    def centroid_rate(self) -> float:
        """Paper-style ORR in [0, 1]; NaN without agent-steps."""
        return self.centroid_steps / self.agent_steps if self.agent_steps else float("nan")

    @property
    def footprint_rate(self) -> float:
        """Footprint ORR in [0, 1]; NaN without agent-steps."""
        return self.footprint_steps / self.agent_steps if self.agent_steps else float("nan")


def overlaps(record: RolloutRecord, tolerance: float = 0.0) -> np.ndarray:
    """Box overlap of every pair at every step, vectorised over time.

    Args:
        record: the rollout.
        tolerance: SAT separation threshold [m] (see
            :func:`riskflow_env.geometry.pair_overlap`); 0 is exact, touching counts.

    Returns:
        (T, A, A) bool, symmetric, False on the diagonal, for invalid agents and at
        context steps.
    """
    states = record.states.transpose(1, 0, 2)  # (T, A, 4)
    valid = record.valid.T & record.scored_steps[:, None]
    return pairwise_overlap(
        states[..., :2], states[..., YAW], record.length, record.width, valid, tolerance
    )


def collisions(record: RolloutRecord, tolerance: float = 0.0) -> CollisionResult:
    """SCR flags of one rollout (``tolerance`` as :func:`overlaps`)."""
    overlap = overlaps(record, tolerance)
    per_step = overlap.any(axis=(1, 2))
    ego = record.ego_index
    ego_steps = overlap[:, ego].any(axis=1) if ego != NO_EGO else np.zeros_like(per_step)
    return CollisionResult(
        collided=bool(per_step.any()),
        ego_collided=bool(ego_steps.any()),
        first_step=int(np.argmax(per_step)) if per_step.any() else -1,
        pairs=overlap.any(axis=0),
        first_ego_step=int(np.argmax(ego_steps)) if ego_steps.any() else -1,
    )


def collision_involvement(pairs: np.ndarray, ego_index: int = NO_EGO) -> np.ndarray:
    """Which agents collided with a non-ego agent (pairs with the ego dropped).

    Args:
        pairs: (A, A) bool, symmetric (``CollisionResult.pairs``).
        ego_index: the ego's slot, or ``NO_EGO``.

    Returns:
        (A,) bool: the agent overlapped some non-ego agent other than itself; always
        False for the ego.
    """
    pairs = np.asarray(pairs, dtype=bool)
    others = np.ones(pairs.shape[0], dtype=bool)
    if ego_index != NO_EGO:
        others[ego_index] = False
    off_diagonal = ~np.eye(pairs.shape[0], dtype=bool)
    return (pairs & off_diagonal & others[:, None] & others[None, :]).any(axis=1)


def collision_rates(results: Sequence[CollisionResult]) -> tuple[float, float]:
    """SCR and the ego-involved collision rate over rollouts.

    Returns:
        (scr, ego_rate): shares of ``results`` in [0, 1]; NaN for an empty list.
    """
    if not results:
        return float("nan"), float("nan")
    scr = float(np.mean([r.collided for r in results]))
    return scr, float(np.mean([r.ego_collided for r in results]))


def footprint_sdf(
    drivable_map: DrivableMap, states: np.ndarray, length: np.ndarray, width: np.ndarray
) -> np.ndarray:
    """Map SDF at the 9 footprint points of every state.

    Args:
        drivable_map: the map.
        states: (A, T, 4) states (x [m], y [m], v [m/s], psi [rad]).
        length: (A,) lengths [m].
        width: (A,) widths [m].

    Returns:
        (A, T, 9) signed distance [m], positive off the drivable area, in
        ``FOOTPRINT_NAMES`` order (index ``CENTRE`` is the box centre).
    """
    points = footprint_points(
        states[..., :2], states[..., YAW], length[:, None], width[:, None]
    )  # (A, T, 9, 2)
    return np.asarray(drivable_map.sdf_at(points))


def offroad_counts(
    centroid: np.ndarray, footprint: np.ndarray, counted: np.ndarray
) -> OffroadResult:
    """ORR counts from per-agent-step off-road flags (module docstring: who passes what).

    Args:
        centroid: (..., ) bool, the box centre is off the drivable area.
        footprint: (..., ) bool, a footprint point is off the drivable area.
        counted: (..., ) bool, the agent-steps that count (ORR's denominator); flags
            outside it are ignored.

    Returns:
        the counts; ``centroid_rate`` / ``footprint_rate`` are the ORRs.
    """
    centroid, footprint, counted = (
        np.asarray(a, dtype=bool) for a in (centroid, footprint, counted)
    )
    if not centroid.shape == footprint.shape == counted.shape:
        raise ValueError(
            "offroad_counts: centroid, footprint and counted must have one shape, got "
            f"{centroid.shape}, {footprint.shape} and {counted.shape}"
        )
    return OffroadResult(
        centroid_steps=int(np.sum(centroid & counted)),
        footprint_steps=int(np.sum(footprint & counted)),
        agent_steps=int(np.sum(counted)),
    )


def offroad(record: RolloutRecord) -> OffroadResult:
    """ORR counts of one rollout over its scored agent-steps (needs ``record.drivable_map``)."""
    if record.drivable_map is None:
        raise ValueError("offroad (ORR) needs a record with a drivable_map")
    outside = footprint_sdf(record.drivable_map, record.states, record.length, record.width) > 0
    return offroad_counts(outside[..., CENTRE], outside.any(axis=-1), record.scored())


def offroad_rates(results: Sequence[OffroadResult]) -> tuple[float, float]:
    """Pooled ORR over rollouts: (centroid, footprint), NaN without agent-steps."""
    pooled = OffroadResult(
        centroid_steps=sum(r.centroid_steps for r in results),
        footprint_steps=sum(r.footprint_steps for r in results),
        agent_steps=sum(r.agent_steps for r in results),
    )
    return pooled.centroid_rate, pooled.footprint_rate
