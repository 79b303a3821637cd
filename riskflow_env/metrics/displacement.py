"""ADE and FDE: position error of simulated vs logged (reference) trajectories.

Per evaluated agent, over the scored steps where both the simulation and the log are
valid (``mask``), with ``e_t = ||xy_t - xy_ref_t||`` [m]:

* ``ADE_a = mean_t e_t`` over the agent's masked steps;
* ``FDE_a = e_t`` at the agent's last masked step.

A rollout's ADE / FDE is the mean over the agents with at least one masked step; over
many rollouts the per-agent values are pooled (every agent of every rollout weighs the
same), as WOSAC's ADE.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from riskflow_env._array import Array, namespace
from riskflow_env._array import device as array_device
from riskflow_env.metrics.rollout import RolloutRecord


@dataclass(frozen=True)
class DisplacementResult:
    """Per-agent displacement errors of one rollout.

    Attributes:
        ade: (A,) average displacement error [m], NaN where ``has_error`` is False.
        fde: (A,) final displacement error [m], NaN where ``has_error`` is False.
        has_error: (A,) bool, the agent is evaluated and has a masked step.
    """

    ade: np.ndarray
    fde: np.ndarray
    has_error: np.ndarray

    @property
    def num_agents(self) -> int:
        """Agents with an error."""
        return int(np.sum(self.has_error))

    @property
    def mean_ade(self) -> float:
        """Mean ADE over agents [m]; NaN if none."""
        return float(np.mean(self.ade[self.has_error])) if self.num_agents else float("nan")

    @property
    def mean_fde(self) -> float:
        """Mean FDE over agents [m]; NaN if none."""
        return float(np.mean(self.fde[self.has_error])) if self.num_agents else float("nan")


def position_errors(record: RolloutRecord) -> tuple[np.ndarray, np.ndarray]:
    """Position error at every step and where it counts.

    Returns:
        error: (A, T) ``||xy - xy_ref||`` [m].
        mask: (A, T) bool, evaluated agent, scored step, both tracks valid.
    """
    error = np.linalg.norm(record.states[..., :2] - record.reference[..., :2], axis=-1)
    return error, record.scored(record.valid & record.reference_valid)


def masked_displacement(error: Array, mask: Array) -> tuple[Array, Array, Array]:
    """Per-track ADE and FDE from position errors, for any leading dims (numpy or torch).

    Args:
        error: (..., T) position errors ``e_t`` [m].
        mask: (..., T) bool, the steps that count.

    Returns:
        ``ade`` (...,) mean of ``e_t`` over the masked steps, ``fde`` (...,) ``e_t`` at
        the last masked step (both 0 where no step is masked), and ``has_error`` (...,)
        bool, the track has a masked step.
    """
    xp = namespace(error)
    count = xp.sum(xp.astype(mask, error.dtype), axis=-1)
    ade = xp.sum(xp.where(mask, error, 0.0), axis=-1) / xp.clip(count, min=1.0)
    steps = xp.arange(mask.shape[-1], device=array_device(error))
    last = xp.max(xp.where(mask, steps, -1), axis=-1)  # -1: no masked step
    fde = xp.sum(xp.where(steps == last[..., None], error, 0.0), axis=-1)
    return ade, fde, last >= 0


def displacement_errors(record: RolloutRecord) -> DisplacementResult:
    """Per-agent ADE and FDE of one rollout."""
    error, mask = position_errors(record)
    ade, fde, has_error = masked_displacement(error, mask)
    return DisplacementResult(
        ade=np.where(has_error, ade, np.nan), fde=np.where(has_error, fde, np.nan),
        has_error=has_error,
    )  # fmt: skip


def displacement_means(results: Sequence[DisplacementResult]) -> tuple[float, float]:
    """Pooled (ADE, FDE) [m] over all agents of all rollouts; NaN if none."""
    ade = [r.ade[r.has_error] for r in results]
    fde = [r.fde[r.has_error] for r in results]
    if not sum(a.size for a in ade):
        return float("nan"), float("nan")
    return float(np.mean(np.concatenate(ade))), float(np.mean(np.concatenate(fde)))


def standstill_drift(
    record: RolloutRecord, still_distance: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """How far the vehicles that stand still in the log are moved by the simulation.

    A vehicle *stands still* when it is evaluated and every logged position over the
    scored steps lies within ``still_distance`` [m] of its logged position at the first
    scored step (parked cars, a queue that never moves). Its drift is the largest
    ``||xy - xy_ref||`` over the scored steps where both tracks are valid.

    Returns:
        ``(still, drift)``: (A,) bool, the vehicle stands still in the log and has a
        masked step; (A,) largest position error [m], NaN where ``still`` is False.
    """
    if not still_distance >= 0:
        raise ValueError(f"still_distance must be >= 0 [m], got {still_distance!r}")
    error, mask = position_errors(record)
    logged = record.scored(record.reference_valid)
    first = np.argmax(logged, axis=1)
    start = record.reference[np.arange(logged.shape[0]), first, :2]
    spread = np.linalg.norm(record.reference[..., :2] - start[:, None], axis=-1)
    still = logged.any(axis=1) & np.all(~logged | (spread <= still_distance), axis=1)
    still &= mask.any(axis=1)
    drift = np.where(still, np.where(mask, error, 0.0).max(axis=1), np.nan)
    return still, drift
