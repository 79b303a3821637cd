"""Whether simulated traffic keeps moving: the counter-metrics of safety.

Traffic that stops never collides, so every collision and off-road rate needs these
beside it. All are per evaluated vehicle, over the scored steps where both the
simulation and the log are valid (the mask of ADE, :func:`position_errors`):

* **progress**: the path length the simulation drives (sum of ``||xy_t - xy_{t-1}||``
  over consecutive masked steps) over the path length of the log on the same steps,
  for the vehicles that move in the log (a logged path over :data:`MOVER_DISTANCE`);
* **stalled**: a log-mover whose progress is below :data:`STALL_PROGRESS`, whatever holds
  it (nothing here looks at what stands in front);
* **turned in place**: a vehicle that stands still in the log
  (:func:`~riskflow_env.metrics.displacement.standstill_drift`) and that the
  simulation turns by more than :data:`TURN_IN_PLACE` from its logged heading while
  keeping it within :data:`PLACE_RADIUS` (a parked car spun in its bay: the
  "moved > 2 m" metric does not see it);
* **hard at the map's edge**: of the vehicle-steps heading for the border of the map's
  raster less than :data:`EDGE_REACH` ahead (along the heading: roads leave the map
  there, running through its margin to the border and on beyond it), the share with
  |longitudinal| or |lateral acceleration| over :data:`HARD_ACCELERATION`
  (:func:`~riskflow_env.metrics.kinematics.kinematic_series`): vehicles that reach the
  end of the map should leave or keep going, not brake and turn. The log's share on the
  same slots is kept beside it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from riskflow_env.dynamics import wrap_angle
from riskflow_env.metrics.displacement import position_errors, standstill_drift
from riskflow_env.metrics.kinematics import kinematic_series
from riskflow_env.metrics.rollout import RolloutRecord

MOVER_DISTANCE = 2.0  # [m] logged path over which a vehicle moves in the log
STALL_PROGRESS = 0.5  # progress below which a log-mover is stalled
TURN_IN_PLACE = np.radians(20.0)  # [rad] heading change of a parked car turned in place
PLACE_RADIUS = 2.0  # [m] a parked car kept within this of its log has not moved
EDGE_REACH = 15.0  # [m] from the border of the map's raster
HARD_ACCELERATION = 3.0  # [m/s^2] |longitudinal| or |lateral|


@dataclass(frozen=True)
class ProgressResult:
    """Per-vehicle progress of one rollout (module docstring).

    Attributes:
        driven: (A,) simulated path length over the masked steps [m].
        logged: (A,) logged path length over the same steps [m].
        mover: (A,) bool, evaluated and ``logged > MOVER_DISTANCE``.
        parked: (A,) bool, stands still in the log (and has a masked step).
        turned: (A,) bool, parked and turned in place by the simulation.
        edge_steps: (simulated, logged) vehicle-steps within ``EDGE_REACH`` of the border.
        edge_hard: (simulated, logged) of those, the steps over ``HARD_ACCELERATION``.
    """

    driven: np.ndarray
    logged: np.ndarray
    mover: np.ndarray
    parked: np.ndarray
    turned: np.ndarray
    edge_steps: tuple[int, int]
    edge_hard: tuple[int, int]

    @property
    def ratio(self) -> np.ndarray:
        """(A,) progress (driven / logged) of the log-movers, NaN for the others."""
        return np.where(self.mover, self.driven / np.where(self.mover, self.logged, 1.0), np.nan)

    @property
    def stalled(self) -> np.ndarray:
        """(A,) bool, a log-mover with progress below ``STALL_PROGRESS``."""
        return self.mover & (np.nan_to_num(self.ratio, nan=1.0) < STALL_PROGRESS)


def progress(record: RolloutRecord) -> ProgressResult:
    """Progress, stalls, parked cars turned in place and manoeuvres at the map's edge of
    one rollout (module docstring). Without ``record.drivable_map`` the edge counts are 0."""
    _, mask = position_errors(record)
    pairs = mask[:, 1:] & mask[:, :-1]

    def path(states: np.ndarray) -> np.ndarray:
        steps = np.linalg.norm(np.diff(states[..., :2], axis=1), axis=-1)
        return np.where(pairs, steps, 0.0).sum(axis=1)

    driven, logged = path(record.states), path(record.reference)
    mover = record.evaluated & (logged > MOVER_DISTANCE)
    parked, drift = standstill_drift(record)
    turn = np.abs(wrap_angle(record.states[..., 3] - record.reference[..., 3]))
    turned = parked & (np.where(mask, turn, 0.0).max(axis=1) > TURN_IN_PLACE)
    turned &= np.nan_to_num(drift, nan=np.inf) <= PLACE_RADIUS
    near, hard = zip(*(
        _edge_counts(record, states, valid)
        for states, valid in ((record.states, record.valid),
                              (record.reference, record.reference_valid))
    ), strict=True)  # fmt: skip
    return ProgressResult(driven, logged, mover, parked, turned, near, hard)


def _edge_counts(record: RolloutRecord, states: np.ndarray, valid: np.ndarray) -> tuple:
    """(steps near the map's border, of them hard) of one set of tracks."""
    if record.drivable_map is None:
        return 0, 0
    series = kinematic_series(states, valid, record.dt)
    accel, ok = series["longitudinal_acceleration"]
    lateral, _ = series["lateral_acceleration"]
    counted = ok & record.scored(valid)[:, 1:] & (_ahead(record, states[:, 1:]) < EDGE_REACH)
    harsh = (np.abs(accel) > HARD_ACCELERATION) | (np.abs(lateral) > HARD_ACCELERATION)
    return int(counted.sum()), int((counted & harsh).sum())


def _ahead(record: RolloutRecord, states: np.ndarray) -> np.ndarray:
    """(...) distance [m] from each state along its heading to the raster's border."""
    low, high = np.split(np.asarray(record.drivable_map.bounds, dtype=float), 2)
    xy = states[..., :2]
    direction = np.stack([np.cos(states[..., 3]), np.sin(states[..., 3])], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = np.where(direction > 0, high - xy, low - xy) / direction
    return np.where(direction == 0, np.inf, reach).clip(min=0.0).min(axis=-1)
