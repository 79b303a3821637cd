"""``record_of``: a ``RolloutRecord`` of hand-made tracks for the metric tests."""

from __future__ import annotations

import numpy as np

from riskflow_env.metrics import RolloutRecord


def record_of(
    states: np.ndarray,
    reference: np.ndarray,
    reference_valid: np.ndarray | None = None,
    length: float = 4.0,
    width: float = 2.0,
    **kwargs,
) -> RolloutRecord:
    """``states`` (A, T, 4) against ``reference`` (A, T, 4), every agent a ``length`` x
    ``width`` [m] box; ``valid`` and ``reference_valid`` default to all True; ``kwargs``:
    the other ``RolloutRecord`` fields."""
    num_agents, num_steps = states.shape[:2]
    if reference_valid is None:
        reference_valid = np.ones((num_agents, num_steps), bool)
    kwargs.setdefault("valid", np.ones((num_agents, num_steps), bool))
    return RolloutRecord(
        states=states,
        length=np.full(num_agents, length),
        width=np.full(num_agents, width),
        reference=reference,
        reference_valid=reference_valid,
        **kwargs,
    )
