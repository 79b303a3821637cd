"""The braking fallback of the avoidance steps (``brake_to_clear``): a vehicle whose plan
still runs into a box ahead of it brakes to stop short of it; the box ahead, vehicles
with a clear plan and vehicles that may not brake keep their plans."""

from __future__ import annotations

import torch

from policies.learned.data import ActionNormalizer
from policies.learned.guidance_losses import HUMAN_ACCEL
from policies.learned.plan_avoidance import (
    BRAKE_JERK,
    BRAKE_MARGIN,
    EGO_STANDS_BELOW,
    avoid_overlaps,
    brake_to_clear,
)
from policies.learned.plan_overlap import pair_separation, scored_pairs
from policies.learned.sampler import decode_plans
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import rollout

DYNAMICS = DynamicsConfig()
NORMALIZER = ActionNormalizer(mean=(0.0, 0.0), std=(1.0, 0.1))
STEPS = 40


def _queue(leader_speed: float = 0.0):
    """The ego far away; a car at 15 m/s behind a car 30 m ahead in its lane, driving at
    ``leader_speed``; every plan holds its speed (zero actions)."""
    state = torch.tensor(
        [[[0.0, 50.0, 10.0, 0.0], [0.0, 0.0, 15.0, 0.0], [30.0, 0.0, leader_speed, 0.0]]],
        dtype=torch.float64,
    )
    actions = torch.zeros(1, 3, STEPS, 2, dtype=torch.float64)
    trajectories = rollout(state, actions, DYNAMICS)
    length = torch.full((1, 3), 4.5, dtype=torch.float64)
    width = torch.full((1, 3), 1.8, dtype=torch.float64)
    mask = torch.ones(1, 3, dtype=torch.bool)
    return actions, trajectories, state, length, width, mask


def _variables(state, mask):
    variable = mask & (state[..., 2] > 0.2)
    variable[:, 0] = False
    return variable


def test_the_follower_stops_short_of_a_standing_car():
    actions, trajectories, state, length, width, mask = _queue()
    pairs = scored_pairs(length, width, mask, state)
    before = (actions.clone(), trajectories.clone())
    rows = brake_to_clear(
        actions, trajectories, state, pairs, length, width, _variables(state, mask), DYNAMICS
    )
    assert rows.tolist() == [1]
    # from its plan's first action the follower's braking grows at BRAKE_JERK to one
    # constant rate, within the human bound, and it stops short
    accel = actions[0, 1, :, 0]
    assert float(accel[0]) == 0.0
    onset = accel[1:3]
    torch.testing.assert_close(onset, -BRAKE_JERK * DYNAMICS.dt * torch.tensor([1.0, 2.0]).double())
    rate = accel[-1]
    assert 0 < -float(rate) <= HUMAN_ACCEL and torch.equal(accel[3:], rate.expand(STEPS - 3))
    gaps = pair_separation(trajectories, length, width)[0, 1, 2]
    assert float(gaps.min()) > 0.0
    assert float(trajectories[0, 1, -1, 2]) == 0.0  # at rest
    torch.testing.assert_close(
        trajectories[0, 1], rollout(state[0, 1:2], actions[0, 1:2], DYNAMICS)[0]
    )
    # the standing car and the ego keep their plans
    for row in (0, 2):
        assert torch.equal(actions[0, row], before[0][0, row])
        assert torch.equal(trajectories[0, row], before[1][0, row])


def test_it_stops_the_margin_short_of_its_last_clear_position():
    """Braking at ``v0^2 / (2 d)`` over the distance ``d`` to the last clear position less
    the margin: the stop lies within a step's travel of that point."""
    actions, trajectories, state, length, width, mask = _queue()
    planned = trajectories.clone()
    pairs = scored_pairs(length, width, mask, state)
    brake_to_clear(
        actions, trajectories, state, pairs, length, width, _variables(state, mask), DYNAMICS
    )
    gaps = pair_separation(planned[..., :30, :], length, width)[0, 1, 2]
    last_clear = int(torch.nonzero(gaps < 0)[0]) - 1
    target = float(planned[0, 1, last_clear, 0]) - BRAKE_MARGIN
    stop = float(trajectories[0, 1, -1, 0])
    assert abs(stop - target) < 15.0 * DYNAMICS.dt


def test_clear_plans_and_cars_that_may_not_brake_are_left_alone():
    """The leader drives away at the follower's speed: nothing overlaps, nothing changes;
    with the follower not a variable (e.g. it is a guided car), it does not brake."""
    actions, trajectories, state, length, width, mask = _queue(leader_speed=15.0)
    pairs = scored_pairs(length, width, mask, state)
    before = (actions.clone(), trajectories.clone())
    rows = brake_to_clear(
        actions, trajectories, state, pairs, length, width, _variables(state, mask), DYNAMICS
    )
    assert rows.numel() == 0
    assert torch.equal(actions, before[0]) and torch.equal(trajectories, before[1])
    actions, trajectories, state, length, width, mask = _queue()
    variable = _variables(state, mask)
    variable[0, 1] = False
    rows = brake_to_clear(actions, trajectories, state, pairs, length, width, variable, DYNAMICS)
    assert rows.numel() == 0


def test_the_avoidance_steps_return_the_braked_plans_and_their_residual():
    """Through ``avoid_overlaps``: the follower's returned plan keeps clear of the standing
    car, and ``u`` decodes to the returned actions (to float rounding); zero steps (the
    raw base) do not brake."""
    _, _, state, length, width, mask = _queue()
    eps = torch.zeros(1, 3, STEPS, 2, dtype=torch.float64)
    args = (eps, torch.zeros_like(eps), state, length, width, mask, None, NORMALIZER, DYNAMICS)
    u, actions, trajectories = avoid_overlaps(*args, steps=5, step_size=0.05)
    assert float(pair_separation(trajectories, length, width)[0, 1, 2].min()) > 0.0
    decoded = decode_plans(eps + u, state, mask, NORMALIZER, DYNAMICS)
    torch.testing.assert_close(decoded[0], actions)
    torch.testing.assert_close(decoded[1], trajectories)
    _, _, raw = avoid_overlaps(*args, steps=0, step_size=0.05)
    assert float(pair_separation(raw, length, width)[0, 1, 2].min()) < 0.0
    # a guided follower (A_c) is left to guidance
    guided = torch.tensor([[False, True, False]])
    _, _, unbraked = avoid_overlaps(*args, steps=5, step_size=0.05, guided=guided)
    _, _, stepped = avoid_overlaps(*args, steps=5, step_size=0.05, brake=False)
    assert torch.equal(unbraked, stepped)


def _follower_behind_the_ego(ego_speed: float):
    """A car at 15 m/s 30 m behind the ego; the ego's predicted plan (its row: the
    generator's guess) accelerates away at 3 m/s^2; a third car far away."""
    state = torch.tensor(
        [[[30.0, 0.0, ego_speed, 0.0], [0.0, 0.0, 15.0, 0.0], [0.0, 60.0, 10.0, 0.0]]],
        dtype=torch.float64,
    )
    eps = torch.zeros(1, 3, STEPS, 2, dtype=torch.float64)
    eps[0, 0, :, 0] = 3.0
    length = torch.full((1, 3), 4.5, dtype=torch.float64)
    width = torch.full((1, 3), 1.8, dtype=torch.float64)
    mask = torch.ones(1, 3, dtype=torch.bool)
    return eps, state, length, width, mask


def test_a_follower_keeps_clear_of_a_slow_ego_where_it_stands():
    """The ego's row is a guess: behind an ego slower than ``EGO_STANDS_BELOW`` the
    follower keeps clear of the ego's current box, as if it stayed; the ego's returned row
    is still the guess. Behind a faster ego it trusts the guess."""
    for ego_speed, brakes in ((1.0, True), (EGO_STANDS_BELOW + 0.5, False)):
        eps, state, length, width, mask = _follower_behind_the_ego(ego_speed)
        args = (eps, torch.zeros_like(eps), state, length, width, mask, None, NORMALIZER)
        _, actions, trajectories = avoid_overlaps(*args, DYNAMICS, steps=5, step_size=0.05)
        zero = torch.zeros_like(eps)
        predicted = decode_plans(eps + zero, state, mask, NORMALIZER, DYNAMICS)[1]
        assert torch.equal(trajectories[0, 0], predicted[0, 0])
        standing = state[:, None, 0].clone()
        standing[..., 2] = 0.0
        follower = trajectories[:, 1:2]
        pair = torch.cat([standing[:, :, None].expand_as(follower), follower], dim=1)
        gaps = pair_separation(pair, length[:, :2], width[:, :2])[0, 0, 1]
        assert (float(gaps.min()) > 0.0) == brakes
        assert bool((actions[0, 1, :, 0] < 0).any()) == brakes
