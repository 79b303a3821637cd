"""Lane geometry: position/project round trips, numpy == torch, surface polygon, errors."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
import torch

from riskflow_env.maps import Lane, lane_polygon, road_polygons
from riskflow_env.maps.surface import junction_polygon


def _arc_lane(radius: float = 20.0, n: int = 60) -> Lane:
    """Counter-clockwise quarter circle around the origin, starting at (radius, 0)."""
    phi = np.linspace(0.0, np.pi / 2, n)
    centerline = radius * np.stack([np.cos(phi), np.sin(phi)], axis=1)
    return Lane(centerline, width=4.0, lane_id="arc", speed_limit=10.0, successors=["next"])


def test_straight_lane_position_and_project() -> None:
    lane = Lane(np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 0.0], [10.0, 5.0]]), 3.5, "l")
    assert lane.centerline.shape == (3, 2)  # repeated point dropped
    assert lane.length == pytest.approx(15.0)
    np.testing.assert_allclose(lane.arclength, [0.0, 10.0, 15.0])
    xy, heading = lane.position(np.array([-1.0, 4.0, 12.0, 99.0]))
    np.testing.assert_allclose(xy, [[0, 0], [4, 0], [10, 2], [10, 5]])
    np.testing.assert_allclose(heading, [0, 0, np.pi / 2, np.pi / 2])
    s, lateral = lane.project(np.array([[4.0, 1.5], [4.0, -2.0], [11.0, 3.0], [13.0, 5.0]]))
    np.testing.assert_allclose(s, [4.0, 4.0, 13.0, 15.0])
    # left of travel is positive; beyond the end, |lateral| is the distance to the end point
    np.testing.assert_allclose(lateral, [1.5, -2.0, -1.0, -3.0])


def test_round_trip_on_arc_numpy_and_torch() -> None:
    lane = _arc_lane()
    rng = np.random.default_rng(0)
    s = rng.uniform(0.5, lane.length - 0.5, size=(4, 25))
    offset = rng.uniform(-1.5, 1.5, size=(4, 25))
    xy, heading = lane.position(s)
    left = np.stack([-np.sin(heading), np.cos(heading)], axis=-1)
    points = xy + offset[..., None] * left
    s_back, lateral = lane.project(points)
    # a polyline, not a circle: on the inner side a point may be nearer to the next
    # segment (segments turn by 1.5 deg here), which shifts s by a few cm at most
    np.testing.assert_allclose(s_back, s, atol=0.05)
    np.testing.assert_allclose(lateral, offset, atol=1e-3)
    back, _ = lane.position(s_back)
    distance = np.linalg.norm(points - back, axis=-1)
    np.testing.assert_allclose(distance, np.abs(lateral), atol=1e-9)
    s_t, lateral_t = lane.project(torch.as_tensor(points))
    np.testing.assert_allclose(s_t.numpy(), s_back, atol=1e-9)
    np.testing.assert_allclose(lateral_t.numpy(), lateral, atol=1e-9)
    xy_t, heading_t = lane.position(torch.as_tensor(s))
    np.testing.assert_allclose(xy_t.numpy(), xy, atol=1e-9)
    np.testing.assert_allclose(heading_t.numpy(), heading, atol=1e-9)
    assert lane.successors == ("next",)


def test_project_is_differentiable() -> None:
    lane = _arc_lane()
    xy = torch.tensor([[25.0, 3.0]], dtype=torch.float64, requires_grad=True)
    _, lateral = lane.project(xy)
    lateral.sum().backward()
    # outside the counter-clockwise arc the left normal points to the centre
    direction = xy.detach()[0] / xy.detach()[0].norm()
    np.testing.assert_allclose(xy.grad[0].numpy(), -direction.numpy(), atol=2e-2)


def test_lane_polygon_has_exact_width_and_flat_ends() -> None:
    lane = Lane(np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]]), 4.0, "corner")
    polygon = lane_polygon(lane)
    assert polygon.is_valid
    assert polygon.bounds == pytest.approx((0.0, -2.0, 12.0, 10.0))  # miter corner, flat ends
    assert polygon.area == pytest.approx(4.0 * 20.0)  # width x centreline length
    arc = lane_polygon(_arc_lane(radius=20.0, n=200))
    assert arc.area == pytest.approx(4.0 * 20.0 * np.pi / 2, rel=1e-3)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"centerline": np.zeros((3, 3))}, "centerline must have shape"),
        ({"centerline": np.zeros((3, 2))}, "2 distinct points"),
        ({"centerline": [[0.0, 0.0], [np.nan, 1.0]]}, "finite"),
        ({"width": 0.0}, "width"),
        ({"width": float("inf")}, "width"),
        ({"lane_id": ""}, "lane_id"),
        ({"speed_limit": -3.0}, "speed_limit"),
        ({"successors": (1,)}, "successors"),
    ],
)
def test_lane_rejects_bad_input(kwargs: dict, match: str) -> None:
    args = {"centerline": [[0.0, 0.0], [1.0, 0.0]], "width": 3.0, "lane_id": "x"} | kwargs
    with pytest.raises(ValueError, match=match):
        Lane(**args)


def test_project_rejects_bad_shape() -> None:
    with pytest.raises(ValueError, match=r"xy must have shape \(\.\.\., 2\)"):
        _arc_lane().project(np.zeros((4, 3)))


def test_junction_patch_closes_a_gap_and_apron_extends_entries() -> None:
    first = Lane([[0.0, 0.0], [10.0, 0.0]], 4.0, "first", successors=("second",))
    second = Lane([[11.0, 1.0], [21.0, 1.0]], 4.0, "second")  # 1 m gap, 1 m sideways
    polygons = road_polygons((first, second))
    patch = junction_polygon(first, second)
    assert len(polygons) == 3 and patch.area > 0
    assert shapely.union_all(polygons).area == pytest.approx(2 * 40.0 + 4.0)  # parallelogram
    plain = Lane([[0.0, 0.0], [10.0, 0.0]], 4.0, "plain", successors=("next",))
    nxt = Lane([[10.0, 0.0], [20.0, 0.0]], 4.0, "next")
    assert junction_polygon(plain, nxt).area == 0.0  # lanes that meet need no patch
    with_apron = shapely.union_all(road_polygons((plain, nxt), entry_apron=5.0))
    assert with_apron.bounds == pytest.approx((-5.0, -2.0, 20.0, 2.0))  # only before "plain"
