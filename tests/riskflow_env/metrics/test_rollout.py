"""RolloutRecord: validation, masks and construction from an env episode."""

from __future__ import annotations

import numpy as np
import pytest

from riskflow_env import simulator
from riskflow_env.config import DynamicsConfig
from riskflow_env.metrics import NO_EGO, RolloutRecord, displacement_errors, rollout_metrics
from riskflow_env.scenarios import Scenario

HISTORY = 5  # scenario history steps, the current one included
FUTURE = 20


def fields(num_agents=2, num_steps=6):
    return dict(
        states=np.zeros((num_agents, num_steps, 4)),
        valid=np.ones((num_agents, num_steps), bool),
        length=np.full(num_agents, 4.0),
        width=np.full(num_agents, 2.0),
        reference=np.zeros((num_agents, num_steps, 4)),
        reference_valid=np.ones((num_agents, num_steps), bool),
    )


def test_validation_messages_name_the_field():
    with pytest.raises(ValueError, match="states"):
        RolloutRecord(**{**fields(), "states": np.zeros((2, 6, 3))})
    with pytest.raises(ValueError, match="reference_valid"):
        RolloutRecord(**{**fields(), "reference_valid": np.ones((2, 5), bool)})
    with pytest.raises(ValueError, match="num_context"):
        RolloutRecord(**fields(), num_context=6)
    with pytest.raises(ValueError, match="ego_index"):
        RolloutRecord(**fields(), ego_index=2)
    for changes, message in (
        ({"dt": "a"}, "RolloutRecord.dt must be a number, got 'a'"),
        ({"num_context": 1.5}, "RolloutRecord.num_context must be an int, got 1.5"),
        ({"ego_index": True}, "RolloutRecord.ego_index must be an int, got True"),
    ):
        with pytest.raises(ValueError) as error:
            RolloutRecord(**fields(), **changes)
        assert str(error.value) == message
    assert RolloutRecord(**fields(), dt=np.float32(0.1), ego_index=np.int64(1)).ego_index == 1
    assert type(RolloutRecord(**fields(), dt=np.float32(0.1)).dt) is float  # 0.1, not 0.1000...1
    assert RolloutRecord(**fields(), dt=np.float32(0.1)).dt == 0.1
    bad = fields()
    bad["states"][0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        RolloutRecord(**bad)


@pytest.mark.reliability
@pytest.mark.parametrize("name", ["valid", "reference_valid", "evaluated"])
@pytest.mark.parametrize("fill", [0.5, 1.0, 1])
def test_masks_must_hold_bools(name, fill):
    """valid=0.5 was read as True; the masks take bools only, naming the field."""
    raw = fields()
    raw[name] = np.full(raw["valid"].shape if name != "evaluated" else 2, fill)
    with pytest.raises(ValueError, match=rf"RolloutRecord\.{name} must hold bools.*got dtype"):
        RolloutRecord(**raw)
    raw[name] = raw[name].astype(bool).tolist()  # a list of bools is taken
    assert RolloutRecord(**raw).valid.dtype == np.bool_


def test_invalid_values_are_zeroed_and_arrays_read_only():
    raw = fields()
    raw["reference"][1, 3] = np.nan
    raw["reference_valid"][1, 3] = False
    record = RolloutRecord(**raw, num_context=2)
    assert np.all(record.reference[1, 3] == 0.0) and not record.states.flags.writeable
    assert record.evaluated.all() and record.ego_index == NO_EGO
    assert record.scored_steps.tolist() == [False, False, True, True, True, True]
    assert record.scored(record.reference_valid).sum() == 7


def straight_scenario(road) -> Scenario:
    steps = HISTORY + FUTURE
    states = np.zeros((3, steps, 4))
    states[:, :, 0] = np.array([[2.0], [12.0], [22.0]]) + 0.8 * np.arange(steps)
    states[:, :, 2] = 8.0
    valid = np.ones((3, steps), bool)
    valid[2, :HISTORY] = False  # agent 2 appears after the current step: not selected
    return Scenario(road, states, valid, np.full(3, 4.0), np.full(3, 2.0), ego_index=1,
                    history_steps=HISTORY, name="box")  # fmt: skip


def test_from_scenario_aligns_an_episode_with_its_log(road):
    scenario = straight_scenario(road)
    state = simulator.reset(scenario, max_agents=3)
    currents, present = [state.current], [state.present]
    keep_speed = np.zeros((3, 2))
    for _ in range(8):
        state = simulator.step(state, keep_speed, DynamicsConfig())
        currents.append(state.current)
        present.append(state.present)
    record = RolloutRecord.from_scenario(scenario, currents, present, history=2)
    assert record.states.shape == (3, 11, 4) and record.num_context == 3
    assert record.ego_index == 0 and record.scene_id == "box"  # the ego is slot 0
    assert not record.valid[2].any() and not record.reference_valid[2].any()  # empty slot
    np.testing.assert_allclose(record.reference[:2], scenario.states[[1, 0], 2:13])
    np.testing.assert_allclose(record.states[:2, :3], scenario.states[[1, 0], 2:5])
    # Keeping the logged constant speed reproduces the log: zero displacement error.
    assert displacement_errors(record).mean_ade == pytest.approx(0.0, abs=1e-9)
    row = rollout_metrics(record)
    assert row["collision"] == 0.0 and row["agent_steps"] == 16.0  # 2 agents x 8 steps


def test_from_scenario_pads_beyond_the_log(road):
    scenario = straight_scenario(road)
    long = np.zeros((3, FUTURE + 5, 4))
    record = RolloutRecord.from_scenario(scenario, long, history=HISTORY + 1)
    assert not record.reference_valid[:, 0].any()  # before the log starts
    assert not record.reference_valid[:, -4:].any() and record.reference_valid[:2, -5].all()
    assert record.valid[:2, HISTORY + 1 :].all() and not record.valid[:2, 0].any()


@pytest.mark.reliability
def test_from_scenario_valid_must_hold_bools(road):
    scenario = straight_scenario(road)
    with pytest.raises(ValueError, match=r"^valid must hold bools.*got dtype float64"):
        RolloutRecord.from_scenario(scenario, np.zeros((3, 4, 4)), np.full(3, 0.5))


def test_from_scenario_takes_harness_rows_with_empty_slots(road):
    scenario = straight_scenario(road)
    states = np.zeros((4, 6, 4))
    states[1] = scenario.states[0, HISTORY - 1 : HISTORY + 5]
    rows = np.array([1, 0, -1, -1])  # ego first, then row 0; slots 2, 3 empty
    present = np.array([True, True, False, False])
    record = RolloutRecord.from_scenario(scenario, states, present, rows, history=0)
    assert record.valid.shape == (4, 6) and record.valid[:2].all() and not record.valid[2:].any()
    assert record.ego_index == 0 and record.num_context == 1
    np.testing.assert_allclose(record.reference[1], scenario.states[0, HISTORY - 1 : HISTORY + 5])
    assert displacement_errors(record).ade[1] == pytest.approx(0.0)
