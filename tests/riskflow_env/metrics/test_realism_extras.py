"""Per-vehicle collision involvement and jerk by phase of the re-plan cycle, on hand-made cases."""

from __future__ import annotations

import numpy as np
import pytest

from riskflow_env.metrics import NO_EGO, collision_involvement, jerk_steps
from tests.riskflow_env.metrics.records import record_of


def test_collision_involvement_drops_pairs_with_the_ego():
    pairs = np.zeros((5, 5), bool)
    pairs[0, 1] = pairs[1, 0] = True  # ego with 1
    pairs[2, 3] = pairs[3, 2] = True  # two non-ego vehicles
    pairs[4, 4] = True  # a diagonal entry is no collision
    assert collision_involvement(pairs, ego_index=0).tolist() == [False, False, True, True, False]
    assert collision_involvement(pairs, NO_EGO).tolist() == [True, True, True, True, False]


def test_jerk_spikes_only_at_the_replan_phase(rolled):
    period, context, steps = 5, 3, 33  # 2 history steps + the reset state, 30 simulated steps
    sim_step = np.arange(steps - 1) - (context - 1)  # action r is simulated step r - context + 1
    accel = np.where(sim_step >= 0, (sim_step // period) % 2, 0).astype(float)  # 0/1 per plan
    track = rolled(np.array([0.0, 0.0, 10.0, 0.0]), np.stack([accel, 0 * accel], axis=1))
    record = record_of(track[None], track[None], num_context=context)
    jerk, step = jerk_steps(record)
    assert step.tolist() == list(range(30))  # simulated steps 0..29: one jerk each
    phase = step % period
    assert np.abs(jerk[phase != 0]).max() == pytest.approx(0.0, abs=1e-9)
    spikes = np.abs(jerk[phase == 0])
    assert spikes[0] == pytest.approx(0.0, abs=1e-9)  # step 0: log (0) -> first plan (0)
    assert spikes[1:] == pytest.approx(10.0)  # |1 - 0| m/s^2 / 0.1 s at every later switch
