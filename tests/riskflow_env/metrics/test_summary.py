"""Per-rollout rows aggregate to the same numbers as the functions over records."""

from __future__ import annotations

import json

import numpy as np
import pytest

from riskflow_env.metrics import (
    ROLLOUT_KEYS,
    KinematicSamples,
    RolloutRecord,
    aggregate_rollout_metrics,
    collision_rates,
    collisions,
    displacement_errors,
    displacement_means,
    kdd_over_records,
    kinematic_samples,
    method_metrics,
    offroad,
    offroad_rates,
    rollout_metrics,
)


def records(road, straight):
    out = []
    for shift, gap in ((0.0, 2.0), (1.5, 30.0), (4.0, 10.0)):
        log = np.stack([straight(5.0, 8.0, 40), straight(5.0 + gap, 8.0, 40)])
        sim = log.copy()
        sim[1, :, 0] -= np.linspace(0.0, 3.0 * shift, 40)  # slot 1 lags, more each rollout
        sim[0, :, 1] += shift  # slot 0 drifts sideways
        out.append(
            RolloutRecord(sim, np.ones((2, 40), bool), np.full(2, 4.0), np.full(2, 2.0), log,
                          np.ones((2, 40), bool), ego_index=0, drivable_map=road, num_context=1)
        )  # fmt: skip
    return out


def test_rows_aggregate_like_the_record_functions(road, straight):
    recs = records(road, straight)
    rows = [json.loads(json.dumps(rollout_metrics(r))) for r in recs]  # through a results file
    assert all(set(row) == set(ROLLOUT_KEYS) for row in rows)
    summary = aggregate_rollout_metrics(rows)
    scr, ego_rate = collision_rates([collisions(r) for r in recs])
    orr, orr_footprint = offroad_rates([offroad(r) for r in recs])
    ade, fde = displacement_means([displacement_errors(r) for r in recs])
    assert summary["scr"] == pytest.approx(scr) and summary["scr"] == pytest.approx(1 / 3)
    assert summary["ego_collision_rate"] == pytest.approx(ego_rate)
    assert (summary["orr"], summary["orr_footprint"]) == pytest.approx((orr, orr_footprint))
    assert (summary["ade"], summary["fde"]) == pytest.approx((ade, fde))
    samples = [KinematicSamples.from_arrays(kinematic_samples(r).as_arrays()) for r in recs]
    table_row = method_metrics(rows, samples)
    assert table_row["kdd"] == pytest.approx(kdd_over_records(recs)["kdd"])
    assert np.isnan(aggregate_rollout_metrics([])["scr"])
