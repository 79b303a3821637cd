"""Vehicles that leave the scene (``EnvConfig.leave_when_log_ends``) are scored while they
are in it: the episode record keeps who is in the scene at every step, on the per-scene
and the batched evaluation path alike (a vehicle that left used to drop out of the record
altogether, its steps before leaving, collisions included, with it)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from policies.evaluation import EvalOptions, plan_jobs
from policies.evaluation.batched import rollout_batch
from policies.evaluation.rollout import rollout_episode
from riskflow_env.scenarios import save_scenario
from riskflow_env.scenarios.scenarionet import scenario_from_description
from tests.riskflow_env.scenarios.scenarionet_sources import description

STEPS = 80  # 8 s: the car's log ends at 6 s


@pytest.fixture(scope="module")
def scenario():
    return scenario_from_description(description("nuscenes"))


@pytest.fixture(scope="module")
def options(scenario, tmp_path_factory):
    bank = tmp_path_factory.mktemp("bank")
    save_scenario(scenario, bank / "00000-nuscenes.npz")
    return EvalOptions(data=str(bank), methods=("replay",), scenes=1, duration=STEPS / 10)


def _episodes(options, scenario, leave: bool):
    (job,) = plan_jobs(replace(options, leave_when_log_ends=leave), [scenario.name])
    episode, record, _ = rollout_episode(job)
    (batched,), _ = rollout_batch([job])
    return episode, record, batched


@pytest.mark.parametrize("leave", [True, False])
def test_a_vehicle_is_scored_until_it_leaves(options, scenario, leave):
    episode, record, batched = _episodes(options, scenario, leave)
    slot = list(episode.scenario_rows).index(scenario.agent_ids.index("car"))
    last = 60 - scenario.current_index  # its last logged step, counted from the reset
    assert episode.states.shape[1] == STEPS + 1
    assert episode.present[slot]
    expected = np.arange(STEPS + 1) <= last if leave else np.ones(STEPS + 1, dtype=bool)
    np.testing.assert_array_equal(episode.in_scene[slot], expected)
    np.testing.assert_array_equal(batched.in_scene, episode.in_scene)
    # the rollout record scores it on exactly those steps (after the logged context)
    context = record.num_context
    assert record.evaluated[slot]
    np.testing.assert_array_equal(record.valid[slot, context:], expected[1:])
    assert record.valid[slot, context - 1]  # the reset state, context
    # the replay drives the log: a vehicle that stays holds its speed past the log's end
    scored = record.valid[slot] & record.reference_valid[slot]
    assert scored.sum() == context + last


def test_a_vehicle_that_left_is_not_in_the_replayable_scenario(options, scenario):
    episode, _, _ = _episodes(options, scenario, True)
    slot = list(episode.scenario_rows).index(scenario.agent_ids.index("car"))
    replayed = episode.to_scenario()
    row = int(np.flatnonzero(episode.present)[:slot].size)  # slot order, the ego first
    future = replayed.valid[row, replayed.current_index + 1 :]
    last = 60 - scenario.current_index
    assert future[:last].all() and not future[last:].any()
