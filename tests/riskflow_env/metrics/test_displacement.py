"""ADE / FDE against references with known offsets."""

from __future__ import annotations

import numpy as np
import pytest

from riskflow_env.metrics import (
    RolloutRecord,
    displacement_errors,
    displacement_means,
    standstill_drift,
)
from tests.riskflow_env.metrics.records import record_of


def test_constant_offset_gives_ade_and_fde_of_its_norm(straight):
    reference = np.stack([straight(0.0, 10.0, 20), straight(5.0, 8.0, 20)])
    shifted = reference.copy()
    shifted[..., :2] += [3.0, 4.0]
    result = displacement_errors(record_of(shifted, reference))
    np.testing.assert_allclose(result.ade, [5.0, 5.0])
    np.testing.assert_allclose(result.fde, [5.0, 5.0])
    assert (result.mean_ade, result.mean_fde) == pytest.approx((5.0, 5.0))


def test_growing_offset_with_context_and_a_log_that_ends_early(straight):
    # Lateral error e_t = t m over 10 steps; step 0 is context.
    reference = straight(0.0, 10.0, 10)[None]
    states = reference.copy()
    states[0, :, 1] = np.arange(10.0)
    full = displacement_errors(record_of(states, reference, num_context=1))
    assert (full.ade[0], full.fde[0]) == pytest.approx((5.0, 9.0))  # mean(1..9), e_9
    log_valid = np.ones((1, 10), bool)
    log_valid[0, 8:] = False  # the log ends at step 7: FDE is taken there
    early = displacement_errors(record_of(states, reference, log_valid, num_context=1))
    assert (early.ade[0], early.fde[0]) == pytest.approx((4.0, 7.0))  # mean(1..7), e_7


def test_agents_without_overlap_with_the_log_and_pooling(straight):
    reference = np.stack([straight(0.0, 10.0, 6), straight(0.0, 10.0, 6)])
    states = reference.copy()
    states[0, :, 0] += 2.0
    log_valid = np.ones((2, 6), bool)
    log_valid[1] = False  # agent 1 has no logged future
    result = displacement_errors(record_of(states, reference, log_valid))
    assert result.has_error.tolist() == [True, False] and np.isnan(result.ade[1])
    assert result.num_agents == 1 and result.mean_ade == pytest.approx(2.0)
    exact = displacement_errors(record_of(reference, reference))  # two agents, error 0
    assert displacement_means([result, exact]) == pytest.approx((2.0 / 3, 2.0 / 3))
    assert np.isnan(displacement_means([])[0])
    not_evaluated = record_of(states, reference, evaluated=np.array([False, True]))
    assert displacement_errors(not_evaluated).num_agents == 1
    assert displacement_errors(not_evaluated).mean_ade == pytest.approx(0.0)


def test_standstill_drift_only_for_vehicles_the_log_keeps_still():
    steps = 6
    reference = np.zeros((3, steps, 4))
    reference[1, :, 0] = np.arange(steps) * 1.0  # moves 5 m in the log
    reference[2, :, 0] = 10.0  # parked at x = 10
    states = reference.copy()
    states[0, :, 0] = np.arange(steps) * 0.5  # parked in the log, driven 2.5 m
    states[2, 3:, 1] = 0.3  # parked, nudged 0.3 m sideways
    valid = np.ones((3, steps), dtype=bool)
    record = RolloutRecord(states, valid, np.full(3, 4.5), np.full(3, 2.0), reference, valid)
    still, drift = standstill_drift(record)
    assert still.tolist() == [True, False, True]
    np.testing.assert_allclose(drift[still], [2.5, 0.3])
    assert np.isnan(drift[1])
    with pytest.raises(ValueError, match="still_distance"):
        standstill_drift(record, still_distance=-1.0)
