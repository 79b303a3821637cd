"""Driving primitives: IDM formula, pure pursuit, arc frame, lane graph lookups."""

from __future__ import annotations

import numpy as np
import pytest

from riskflow_env.agents.controllers import (
    arc_frame,
    idm_acceleration,
    pure_pursuit,
    speed_control,
)
from riskflow_env.agents.lane_graph import LaneGraph
from riskflow_env.compiled import SWITCH
from riskflow_env.config import DynamicsConfig
from riskflow_env.maps import Lane, from_lanes

IDM = dict(accel_max=1.5, decel_comfort=2.0, time_headway=1.5, min_gap=2.0, delta=4.0)


def test_idm_free_road_and_equilibrium():
    free = idm_acceleration(
        np.array([0.0, 20.0]), np.full(2, 20.0), np.full(2, np.inf), np.zeros(2), **IDM
    )
    np.testing.assert_allclose(free, [1.5, 0.0])
    speed, gap = 10.0, 2.0 + 10.0 * 1.5  # s = s* with no closing speed
    accel = idm_acceleration(
        np.array([speed]), np.array([20.0]), np.array([gap]), np.zeros(1), **IDM
    )
    np.testing.assert_allclose(accel, -1.5 * (10.0 / 20.0) ** 4)
    closing = idm_acceleration(
        np.array([speed]), np.array([20.0]), np.array([gap]), np.ones(1), **IDM
    )
    desired_gap = gap + speed * 1.0 / (2 * np.sqrt(1.5 * 2.0))
    np.testing.assert_allclose(closing, 1.5 * (1 - 0.5**4 - (desired_gap / gap) ** 2))


def test_pure_pursuit_turns_toward_the_target_within_bounds():
    state = np.array([[0.0, 0.0, 10.0, 0.0], [0.0, 0.0, 10.0, 0.0], [0.0, 0.0, 2.0, 0.0]])
    target = np.array([[10.0, 0.0], [10.0, -10.0], [10.0, 1.0]])
    yaw_rate = pure_pursuit(state, target, DynamicsConfig(yaw_rate_max=0.5))
    np.testing.assert_allclose(yaw_rate[:2], [0.0, -0.5])
    np.testing.assert_allclose(yaw_rate[2], 2.0 * 2.0 * 1.0 / 101.0)
    np.testing.assert_allclose(speed_control(np.array([5.0]), np.array([7.0]), gain=0.5), [1.0])


def test_arc_frame_on_a_circle():
    radius, angle = 20.0, 0.7
    dx, dy = radius * np.sin(angle), radius * (1 - np.cos(angle))  # left turn, on the arc
    along, lateral, turned = arc_frame(
        np.array([dx, dx]), np.array([dy, -dy]), np.array([1 / radius, -1 / radius])
    )
    np.testing.assert_allclose(along, radius * angle)
    np.testing.assert_allclose(lateral, 0.0, atol=1e-9)
    np.testing.assert_allclose(turned, [angle, -angle])
    straight = arc_frame(np.array([3.0]), np.array([-1.0]), np.array([0.0]))
    np.testing.assert_allclose(np.ravel(straight), [3.0, -1.0, 0.0])


def _fork() -> LaneGraph:
    """a: x 0 -> 50; b continues straight; c turns left; d ends on b (a merge)."""
    arc = 50.0 + 20.0 * np.sin(np.linspace(0, np.pi / 2, 20))
    lanes = [
        Lane(np.array([[0.0, 0.0], [50.0, 0.0]]), 4.0, "a", successors=("c", "b")),
        Lane(np.array([[50.0, 0.0], [150.0, 0.0]]), 4.0, "b"),
        Lane(np.stack([arc, 20.0 - 20.0 * np.cos(np.linspace(0, np.pi / 2, 20))], 1), 4.0, "c"),
        Lane(np.array([[60.0, -30.0], [80.0, -1.0]]), 4.0, "d"),
    ]
    return LaneGraph(from_lanes(lanes))


@pytest.mark.parametrize("switch", ["0", "1"], ids=["numpy", "compiled"])
def test_lane_graph_match_position_and_successors(switch, monkeypatch):
    monkeypatch.setenv(SWITCH, switch)
    graph = _fork()
    lane, s, lateral, error = graph.match(
        np.array([[10.0, 1.0], [10.0, 1.0]]), np.array([0.0, np.pi])
    )
    assert lane[0] == 0 and s[0] == pytest.approx(10.0) and lateral[0] == pytest.approx(1.0)
    assert abs(error[1]) == pytest.approx(np.pi)
    xy, heading = graph.position(np.array([0]), np.array([70.0]))  # straight on: into b
    np.testing.assert_allclose(xy, [[70.0, 0.0]])
    route = np.zeros((1, 4), dtype=bool)
    route[0, 2] = True  # the log turns left
    xy, heading = graph.position(np.array([0]), np.array([50.0 + 10 * np.pi]), route)
    np.testing.assert_allclose(xy, [[70.0, 20.0]], atol=0.1)
    assert heading[0] == pytest.approx(np.pi / 2, abs=0.1)
    assert graph.distance_to_dead_end(np.array([0]), np.array([10.0]))[0] == pytest.approx(140.0)
    # d has no listed successor but ends on b: it merges into b at x = 80
    assert graph.successors[3, 0] == 1 and graph.successors_s[3, 0] == pytest.approx(30.0, abs=0.1)
    xy, _ = graph.position(np.array([3]), np.array([graph.length[3] + 5.0]))
    np.testing.assert_allclose(xy, [[85.0, 0.0]], atol=0.1)
    xy, _ = graph.position(np.array([1]), np.array([110.0]))  # beyond a dead end: straight on
    np.testing.assert_allclose(xy, [[160.0, 0.0]])
    bend = graph.curvature_ahead(
        np.array([0, 0]),
        np.array([45.0, 45.0]),
        np.array([30.0, 30.0]),
        np.array([[False] * 4, route[0]]),
    )
    assert bend[0] == pytest.approx(0.0) and bend[1] > 0.02
