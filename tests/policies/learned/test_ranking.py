"""TTC causal ranking: groups, scores, top-K, ties and shortfalls on known conflicts."""

from __future__ import annotations

import numpy as np
import pytest

from policies.learned.ranking import (
    MIN_ATTACK_SPEED,
    MIN_ATTACKER_SPEED,
    NO_GROUP,
    causal_ranking,
    check_k,
    ego_attacker,
    interaction_groups,
    rank_window,
    risk_graph,
)
from policies.learned.window_types import Window
from riskflow_env.risk import pair_risk


def _risk(num_agents: int, pairs: dict[tuple[int, int], float]) -> np.ndarray:
    risk = np.zeros((num_agents, num_agents))
    for (i, j), value in pairs.items():
        risk[i, j] = value  # one direction only: the graph symmetrises with max
    return risk


# Slots: 0 ego. Chain 1-2-3 (risk 1.7 in all), pair 4-5 (0.95), ego-6 (0.6), loose 7, 8.
CHAIN = {(1, 2): 0.9, (3, 2): 0.8, (4, 5): 0.95, (0, 6): 0.6, (7, 1): 0.4, (8, 0): 0.3}


def test_groups_are_connected_components_of_the_thresholded_graph():
    weights, edges = risk_graph(_risk(9, CHAIN), np.ones(9, bool))
    assert np.allclose(weights, weights.T)
    groups = interaction_groups(edges)
    # 1-3 are one group although 1 and 3 never conflict directly (a causal chain).
    assert groups[1] == groups[2] == groups[3]
    assert groups[4] == groups[5] != groups[1]
    assert groups[0] == groups[6]
    assert groups[7] == groups[8] == NO_GROUP
    assert list(groups[[0, 1, 4]]) == [0, 1, 2]  # labels follow the lowest slot


def test_scores_are_accumulated_group_risk():
    ranking = causal_ranking(_risk(9, CHAIN), np.ones(9, bool), 2)
    assert np.allclose(ranking.scores, [0.6, 1.7, 1.7, 1.7, 0.95, 0.95, 0.6, 0.0, 0.0])


@pytest.mark.parametrize(
    ("k", "expected"),
    [
        (0, []),
        (1, [2]),  # the chain's centre carries the most risk (0.9 + 0.8)
        (2, [1, 2]),
        (3, [1, 2, 3]),
        (5, [1, 2, 3, 4, 5]),
        (6, [1, 2, 3, 4, 5, 6]),  # the ego's partner; the ego itself never
        (7, [1, 2, 3, 4, 5, 6, 7]),  # shortfall: 7 has the larger risk to anyone (0.4 > 0.3)
        (20, [1, 2, 3, 4, 5, 6, 7, 8]),
        ("all", [1, 2, 3, 4, 5, 6, 7, 8]),
    ],
)
def test_top_k(k, expected):
    ranking = causal_ranking(_risk(9, CHAIN), np.ones(9, bool), k)
    assert list(np.flatnonzero(ranking.controllable)) == expected
    assert list(ranking.order) == [2, 1, 3, 4, 5, 6, 7, 8]
    assert not ranking.controllable[0]


def test_ties_go_to_the_agent_nearer_the_ego_then_the_lower_slot():
    risk = _risk(5, {(1, 2): 0.9, (3, 4): 0.9})  # two identical pairs
    valid = np.ones(5, bool)
    assert list(causal_ranking(risk, valid, 4).order) == [1, 2, 3, 4]
    distance = np.array([0.0, 40.0, 30.0, 20.0, 10.0])
    assert list(causal_ranking(risk, valid, 4, distance_to_ego=distance).order) == [4, 3, 2, 1]


def test_ego_and_invalid_agents_are_never_controllable():
    risk = _risk(4, {(0, 1): 1.0, (2, 3): 0.7})
    valid = np.array([True, True, False, True])
    ranking = causal_ranking(risk, valid, "all")
    assert list(np.flatnonzero(ranking.controllable)) == [1, 3]
    assert ranking.groups[2] == NO_GROUP and ranking.scores[3] == 0.0  # its partner is gone
    ego_last = causal_ranking(risk, np.ones(4, bool), "all", ego=3)
    assert not ego_last.controllable[3] and ego_last.controllable[0]


def test_threshold():
    risk = _risk(3, {(0, 1): 0.55, (1, 2): 0.45})
    assert list(causal_ranking(risk, np.ones(3, bool), 1).order) == [1, 2]
    high = causal_ranking(risk, np.ones(3, bool), 1, threshold=0.6)
    assert np.all(high.groups == NO_GROUP) and list(high.order) == [1, 2]  # by largest risk


def test_known_conflict_from_ttc_risk():
    """Ego driving at 20 m/s; a car stopped 30 m ahead in its lane is the conflict
    (TTC ~ 1.3 s); cars in parallel lanes at the same speed are not; two cars on a
    crossing course far behind form their own group."""
    state = np.array(
        [
            [0.0, 0.0, 20.0, 0.0],  # ego
            [30.0, 0.0, 0.0, 0.0],  # stopped ahead
            [0.0, 3.5, 20.0, 0.0],  # parallel, same speed
            [10.0, -3.5, 20.0, 0.0],  # parallel, same speed
            [-40.0, 15.0, 10.0, -np.pi / 2],  # crossing pair behind
            [-40.0, -15.0, 10.0, np.pi / 2],
        ]
    )
    length, width = np.full(6, 4.5), np.full(6, 2.0)
    risk = pair_risk(state, length, width)[0]
    distance = np.linalg.norm(state[:, :2] - state[0, :2], axis=-1)
    ranking = causal_ranking(risk, np.ones(6, bool), 3, distance_to_ego=distance)
    assert ranking.order[0] == 1
    assert set(np.flatnonzero(ranking.controllable)) == {1, 4, 5}
    assert ranking.groups[2] == ranking.groups[3] == NO_GROUP


def _window(features: np.ndarray, history: np.ndarray) -> Window:
    """A live-scene window with these pair features and histories (the rest zero)."""
    num = features.shape[0]
    return Window(
        history=history,
        history_valid=np.ones(history.shape[:2], bool),
        agent_mask=np.ones(num, bool),
        agent_index=np.arange(num),
        length=np.full(num, 4.5, np.float32),
        width=np.full(num, 2.0, np.float32),
        map_crops=np.zeros((num, 2, 8, 8), np.float32),
        pair_features=features,
        pair_mask=np.ones((num, num), bool),
    )


def test_rank_window_uses_the_risk_channel_and_positions():
    num = 4
    features = np.zeros((num, num, 8), np.float32)
    features[2, 3, -1] = features[3, 2, -1] = 0.8
    history = np.zeros((num, 31, 4), np.float32)
    history[:, -1, 0] = [0.0, 5.0, 50.0, 20.0]
    ranking = rank_window(_window(features, history), 1)
    assert list(ranking.order) == [3, 2, 1]  # 3 is nearer the ego than 2
    assert list(np.flatnonzero(ranking.controllable)) == [3]


def test_bad_input():
    for bad in (-1, 1.5, True, "some", None):
        with pytest.raises(ValueError, match="k must be"):
            check_k(bad)
    with pytest.raises(ValueError, match="risk must be"):
        causal_ranking(np.zeros((3, 2)), np.ones(3, bool), 1)
    with pytest.raises(ValueError, match="risk must be"):
        causal_ranking(np.full((2, 2), np.nan), np.ones(2, bool), 1)
    with pytest.raises(ValueError, match="ego"):
        causal_ranking(np.zeros((2, 2)), np.ones(2, bool), 1, ego=2)


def test_rank_window_candidates_restrict_the_choice_not_the_graph():
    num = 4
    features = np.zeros((num, num, 8), np.float32)
    features[1, 2, -1] = features[3, 0, -1] = 0.9
    window = _window(features, np.zeros((num, 31, 4), np.float32))
    candidates = np.array([True, False, True, True])  # 1 is done but still an obstacle
    ranking = rank_window(window, 1, candidates=candidates)
    assert list(ranking.order) == [2, 3] and list(np.flatnonzero(ranking.controllable)) == [2]
    assert ranking.groups[1] == ranking.groups[2] != NO_GROUP


def _ego_scene(positions, speeds, ego_risk=()):
    """A window: the ego at the origin heading +x at ``speeds[0]``, the others at
    ``positions`` (x, y) [m] with ``speeds``; ``ego_risk`` {slot: risk with the ego}."""
    num = len(speeds)
    history = np.zeros((num, 31, 4), np.float32)
    history[1:, -1, :2] = positions
    history[:, -1, 2] = speeds
    features = np.zeros((num, num, 8), np.float32)
    for slot, value in dict(ego_risk).items():
        features[slot, 0, -1] = value
    return _window(features, history)


# Slots: 1 ahead in the lane, 2 beside, 3 behind in the lane, 4 behind in the next lane.
EGO_SCENE = [(20.0, 0.0), (-1.0, 3.5), (-10.0, 0.0), (-8.0, 3.5)]


def test_ego_attacker_is_one_vehicle_ahead_or_beside_never_behind():
    window = _ego_scene(EGO_SCENE, [10.0] * 5, {1: 0.2, 2: 0.1, 3: 0.9, 4: 0.9})
    ranking = rank_window(window, 5)
    assert ranking.controllable.sum() == 4
    attack = ego_attacker(ranking, window, 5, previous=None)
    # 3 and 4 are riskier but behind the ego's rear bumper; 1 is the riskiest of the rest.
    assert list(np.flatnonzero(attack.controllable)) == [1]
    assert list(attack.order) == list(ranking.order)
    no_risk = _ego_scene(EGO_SCENE, [10.0] * 5)
    nearest = ego_attacker(rank_window(no_risk, 5), no_risk, 5, previous=None)
    assert list(np.flatnonzero(nearest.controllable)) == [2]  # no risk: the nearest


def test_ego_attacker_is_kept_while_eligible():
    window = _ego_scene(EGO_SCENE, [10.0] * 5, {1: 0.9, 2: 0.1})
    ranking = rank_window(window, 5)
    kept = ego_attacker(ranking, window, 5, previous=2)
    assert list(np.flatnonzero(kept.controllable)) == [2]  # not the riskier 1
    dropped = ego_attacker(ranking, window, 5, previous=3)  # now behind the ego
    assert list(np.flatnonzero(dropped.controllable)) == [1]


def test_no_attack_on_an_ego_at_rest_or_with_k0():
    window = _ego_scene(EGO_SCENE, [MIN_ATTACK_SPEED - 0.1] + [10.0] * 4, {1: 0.9})
    ranking = rank_window(window, 5)
    assert not ego_attacker(ranking, window, 5, previous=1).controllable.any()
    moving = _ego_scene(EGO_SCENE, [10.0] * 5, {1: 0.9})
    assert not ego_attacker(rank_window(moving, 0), moving, 0, previous=None).controllable.any()


def test_a_vehicle_at_rest_never_attacks():
    # 1 (parked ahead) is the riskiest, 2 (beside, moving) the only one that may attack.
    speeds = [10.0, MIN_ATTACKER_SPEED - 0.1, 10.0, 10.0, 10.0]
    window = _ego_scene(EGO_SCENE, speeds, {1: 0.9, 2: 0.1})
    attack = ego_attacker(rank_window(window, 5), window, 5, previous=1)
    assert list(np.flatnonzero(attack.controllable)) == [2]  # the last attacker stopped too
    parked = _ego_scene(EGO_SCENE, [10.0, 0.0, 0.0, 10.0, 10.0], {1: 0.9, 2: 0.5})
    assert not ego_attacker(rank_window(parked, 5), parked, 5, None).controllable.any()
