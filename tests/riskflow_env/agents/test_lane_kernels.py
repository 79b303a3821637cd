"""The compiled lane lookups (:mod:`riskflow_env.agents.lane_kernels`) against the numpy
reference (:class:`~riskflow_env.agents.lane_graph.LaneGraph`) on shipped maps: the same
lanes and, to float rounding, the same numbers."""

from __future__ import annotations

import numpy as np
import pytest

from riskflow_env import kernel_loading
from riskflow_env.agents import lane_graph
from riskflow_env.agents.lane_graph import LaneGraph
from riskflow_env.compiled import SWITCH
from riskflow_env.scenarios import shipped_bank

pytest.importorskip("numba")


def both(monkeypatch, lookup, *args, **kwargs):
    """``lookup(*args, **kwargs)`` on the numpy reference, then on the kernels."""
    results = []
    for switch in ("0", "1"):
        monkeypatch.setenv(SWITCH, switch)
        results.append(lookup(*args, **kwargs))
    return results


@pytest.mark.parametrize("index", range(6))  # one scene of each road family
def test_compiled_lookups_equal_the_reference(index, monkeypatch):
    scenario = shipped_bank("eval")[index]
    graph = LaneGraph(scenario.map)
    rng = np.random.default_rng(index)
    states = scenario.states[:, ::5][scenario.valid[:, ::5]]
    xy = states[:, :2] + rng.normal(0.0, 1.5, (len(states), 2))  # on, beside and off lanes
    yaw = states[:, 3] + rng.normal(0.0, 0.3, len(states))
    route = rng.random((len(xy), graph.num_lanes)) < 0.3
    for on_route in (None, route):
        reference, compiled = both(monkeypatch, graph.match, xy, yaw, route=on_route)
        np.testing.assert_array_equal(compiled[0], reference[0])
        for mine, theirs in zip(compiled[1:], reference[1:], strict=True):
            np.testing.assert_allclose(mine, theirs, rtol=0, atol=1e-9)
        lane, s = reference[0], reference[1]
        ahead = s[:, None] + rng.uniform(-5.0, 120.0, (len(s), 6))  # across successors
        reference, compiled = both(monkeypatch, graph.position, lane[:, None], ahead, on_route)
        for mine, theirs in zip(compiled, reference, strict=True):
            np.testing.assert_allclose(mine, theirs, rtol=0, atol=1e-9)
        reference, compiled = both(monkeypatch, graph.distance_to_dead_end, lane, s, on_route)
        np.testing.assert_allclose(compiled, reference, rtol=0, atol=1e-9)
        preview = np.full(len(s), 25.0)
        reference, compiled = both(monkeypatch, graph.curvature_ahead, lane, s, preview, on_route)
        np.testing.assert_allclose(compiled, reference, rtol=0, atol=1e-9)


def test_positions_keep_the_query_shape(monkeypatch):
    graph = LaneGraph(shipped_bank("eval")[0].map)
    for query in (np.array(0), np.zeros(3, int), np.zeros((2, 4), int)):
        reference, compiled = both(monkeypatch, graph.position, query, query + 10.0)
        assert compiled[0].shape == reference[0].shape == (*query.shape, 2)
        assert compiled[1].shape == reference[1].shape == query.shape
        np.testing.assert_allclose(compiled[0], reference[0], rtol=0, atol=1e-9)


def test_no_writable_cache_directory_runs_the_reference(monkeypatch):
    from tests.numba_cache import without_writable_cache

    without_writable_cache(monkeypatch, ("riskflow_env.agents.lane_kernels",))
    monkeypatch.setenv(SWITCH, "1")
    kernel_loading._imported.cache_clear()
    try:
        with pytest.warns(RuntimeWarning, match="NUMBA_CACHE_DIR"):
            assert lane_graph.compiled() is None
    finally:
        monkeypatch.undo()
        kernel_loading._imported.cache_clear()
    assert lane_graph.compiled() is not None


def test_edge_queries_give_the_references_answers(monkeypatch):
    """A NaN point in a chunk (numpy then searches every segment), a point at infinity
    (every cost inf: the first segment), no query, a scalar arclength; and invalid lanes
    raise as in numpy."""
    graph = LaneGraph(shipped_bank("eval")[0].map)
    xy = np.array([[20.0, 2.0], [np.nan, 0.0], [np.inf, 0.0]])
    yaw = np.zeros(3)
    reference, compiled = both(monkeypatch, graph.match, xy, yaw)
    for mine, theirs in zip(compiled, reference, strict=True):
        np.testing.assert_array_equal(mine, theirs)
    empty = np.zeros((0, 5), dtype=int)
    reference, compiled = both(monkeypatch, graph.position, empty, empty + 1.0)
    assert compiled[0].shape == reference[0].shape == (0, 5, 2)
    lanes = np.array([0, 1, 1])
    reference, compiled = both(monkeypatch, graph.distance_to_dead_end, lanes, 3.0)
    np.testing.assert_array_equal(compiled, reference)
    for switch in ("0", "1"):
        monkeypatch.setenv(SWITCH, switch)
        with pytest.raises(IndexError):
            graph.position(np.array([graph.num_lanes + 3]), np.array([1.0]))
