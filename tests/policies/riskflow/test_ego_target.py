"""Target ``"ego"`` in closed loop: one attacker at a time, kept across cycles, never on an
ego at rest (``policies.learned.ranking.ego_attacker``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from policies.riskflow.policy import RiskFlowAdversary
from tests.policies.straight_road import (
    ROAD_ENV,
    TINY_NORMALIZER,
    make_road_scenario,
    road_env,
    run_closed_loop,
)

CONFIG = dataclasses.replace(ROAD_ENV, episode_steps=25)


@pytest.fixture
def model(make_model, tiny_config):
    return make_model(tiny_config, seed=1).eval()


def adversary(model, **kwargs) -> RiskFlowAdversary:
    kwargs = {"k": 5, "target": "ego", "guidance_steps": 5, "seed": 3, "threads": 1, **kwargs}
    return RiskFlowAdversary(generator=model, normalizer=TINY_NORMALIZER, **kwargs)


def guided_per_cycle(policy, scenario, steps: int = 20) -> list[np.ndarray]:
    """``policy.controllable`` after each planning cycle of a closed loop on ``scenario``."""
    chosen = []

    def record(view, policy, actions):
        if view.step % 5 == 0:
            chosen.append(policy.controllable.copy())

    run_closed_loop(policy, steps, scenario, CONFIG, record)
    return chosen


def test_ego_target_guides_one_vehicle_and_keeps_it_in_closed_loop(model):
    cycles = guided_per_cycle(adversary(model), make_road_scenario())
    assert len(cycles) == 4
    attackers = {tuple(np.flatnonzero(flags)) for flags in cycles}
    assert len(attackers) == 1  # the same vehicle every cycle (it stays ahead of the ego)
    (attacker,) = attackers.pop()
    assert attacker != 0
    others = guided_per_cycle(adversary(model, target="others"), make_road_scenario())
    assert all(flags.sum() == 5 for flags in others)  # the paper's target: K vehicles


def test_the_last_cycles_attacker_is_kept_while_it_is_ahead_of_the_ego(model):
    policy = adversary(model)
    view = road_env(CONFIG).view()
    policy.reset(view)
    policy.plan(view)
    (first,) = np.flatnonzero(policy.controllable)
    x = view.current[:, 0] - view.current[0, 0]  # [m] along the road, ahead of the ego > 0
    present = np.flatnonzero(view.present)
    ahead = [slot for slot in present if x[slot] > 0 and slot != first]
    behind = [slot for slot in present if x[slot] < -2.25]  # behind the ego's rear bumper
    assert x[first] > 0 and len(ahead) == 2 and behind
    for previous, expected in ((ahead[0], ahead[0]), (ahead[-1], ahead[-1]), (behind[0], first)):
        flags = np.zeros_like(policy.controllable)
        flags[previous] = True
        policy.state = policy.state.replace(controllable=flags)
        policy.plan(view)
        assert list(np.flatnonzero(policy.controllable)) == [expected]


def test_no_attack_on_an_ego_at_rest_in_closed_loop(model):
    scenario = make_road_scenario()
    states = scenario.states.copy()
    states[0, :, 0], states[0, :, 2] = 0.0, 0.0  # the ego stands at the origin
    standing = dataclasses.replace(scenario, states=states)
    cycles = guided_per_cycle(adversary(model), standing)
    assert len(cycles) == 4 and not any(flags.any() for flags in cycles)
