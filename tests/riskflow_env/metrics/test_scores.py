"""CS / RS on a three-method table computed by hand."""

from __future__ import annotations

import math

import pytest

from riskflow_env.metrics import min_max_normalise, safety_realism_scores

TABLE = {
    "a": {"scr": 0.5, "orr": 0.1, "ade": 2.0, "fde": 4.0, "kdd": 0.3},
    "b": {"scr": 0.3, "orr": 0.0, "ade": 1.0, "fde": 3.0, "kdd": 0.1},
    "c": {"scr": 0.1, "orr": 0.2, "ade": 3.0, "fde": 2.0, "kdd": 0.5},
}


def test_three_methods_by_hand():
    scores = safety_realism_scores(TABLE)
    # CS = norm(SCR): a 1, b 0.5, c 0.
    # norm ORR a .5 b 0 c 1; ADE a .5 b 0 c 1; FDE a 1 b .5 c 0; KDD a .5 b 0 c 1.
    expected = {"a": (1.0, 1 - 2.5 / 4), "b": (0.5, 1 - 0.5 / 4), "c": (0.0, 1 - 3.0 / 4)}
    for method, (cs, rs) in expected.items():
        assert scores[method] == {"cs": pytest.approx(cs), "rs": pytest.approx(rs)}


def test_equal_methods_normalise_to_zero():
    equal = {name: dict(metrics, orr=0.05, scr=0.2) for name, metrics in TABLE.items()}
    scores = safety_realism_scores(equal)
    assert all(score["cs"] == 0.0 for score in scores.values())
    # ORR no longer counts: a = 1 - (0 + .5 + 1 + .5) / 4.
    assert scores["a"]["rs"] == pytest.approx(0.5)
    single = safety_realism_scores({"only": TABLE["a"]})
    assert single == {"only": {"cs": 0.0, "rs": 1.0}}


def test_nan_and_missing_metrics():
    normalised = min_max_normalise({"x": 1.0, "y": float("nan"), "z": 3.0})
    assert normalised["x"] == 0.0 and normalised["z"] == 1.0 and math.isnan(normalised["y"])
    with_nan = dict(TABLE, d={**TABLE["a"], "kdd": float("nan")})
    assert math.isnan(safety_realism_scores(with_nan)["d"]["rs"])
    assert safety_realism_scores(with_nan)["a"]["rs"] == pytest.approx(1 - 2.5 / 4)
    for bad in (float("inf"), float("-inf")):  # left out as NaN is: the others keep their span
        with_inf = dict(TABLE, d={**TABLE["a"], "kdd": bad})
        assert math.isnan(safety_realism_scores(with_inf)["d"]["rs"])
        assert safety_realism_scores(with_inf)["a"]["rs"] == pytest.approx(1 - 2.5 / 4)
    with pytest.raises(ValueError, match="lacks"):
        safety_realism_scores({"a": {"scr": 0.1}})
    assert safety_realism_scores({}) == {}
