"""The map beyond its raster: roads that cross the border go on straight, off-road ground
stays off-road and keeps getting farther from the road; the builders open the roads that
leave the map (lane ends on the raster's edge, a crop's cut roads) and keep dead ends."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
import torch

from riskflow_env.maps import DrivableMap, Lane, MapStack, from_lanes, from_polygons
from riskflow_env.maps.rasterize import signed_distance
from tests.riskflow_env.maps.sdf_checks import numeric_sdf_gradient

RES = 0.5  # [m/px]
HALF_ROAD = 4.0  # [m] the road is y in [-4, 4]


@pytest.fixture(scope="module")
def crossing() -> DrivableMap:
    """A straight road along x across the whole raster x in [0, 40], y in [-10, 10]."""
    y = -10.0 + (np.arange(40) + 0.5) * RES
    drivable = np.repeat((np.abs(y) < HALF_ROAD)[:, None], 80, axis=1)
    return DrivableMap(drivable, RES, np.array([0.0, -10.0]))


def test_sdf_ignores_the_raster_edge_where_the_road_crosses_it(crossing: DrivableMap) -> None:
    """No boundary at the raster's edge: the SDF of the road is the same in every column."""
    np.testing.assert_array_equal(crossing.sdf, np.repeat(crossing.sdf[:, 40:41], 80, axis=1))
    np.testing.assert_array_equal(crossing.sdf, signed_distance(crossing.drivable, RES))
    np.testing.assert_allclose(crossing.sdf_at(np.array([[0.1, 0.0], [39.9, 0.0]])), -3.75)
    full = DrivableMap(np.ones((4, 6), dtype=bool), resolution=1.0, origin=np.zeros(2))
    np.testing.assert_array_equal(full.sdf, -10.0)  # no boundary: the raster's size, H + W px
    assert full.is_drivable(np.array([[-50.0, 2.0], [3.0, 80.0], [-9.0, -9.0]])).all()


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_a_road_crossing_the_border_goes_on_beyond_it(crossing: DrivableMap, backend) -> None:
    x = np.array([-200.0, -30.0, -0.1, 40.1, 55.0, 300.0])
    along = np.stack([x, np.full_like(x, 1.0)], axis=-1)  # on the road, 3 m from its edge
    beside = np.stack([x, np.full_like(x, 7.0)], axis=-1)  # 3 m beside the road
    if backend == "torch":
        along, beside = torch.as_tensor(along), torch.as_tensor(beside)
    on_road, off_road = np.asarray(crossing.sdf_at(along)), np.asarray(crossing.sdf_at(beside))
    np.testing.assert_allclose(on_road, -3.0)  # the border pixel's value, out to any distance
    assert (off_road > 0).all() and not np.asarray(crossing.is_drivable(beside)).any()
    # off-road ground keeps growing by the distance out of the raster
    border = np.where(x < 0, 0.25, 39.75)  # [m] x of the outermost pixel centres
    np.testing.assert_allclose(off_road, 3.0 + np.abs(x - border), rtol=1e-12)


def test_gradient_beyond_the_border(crossing: DrivableMap) -> None:
    """On the continued road no pull back into the map (0 along x), across it the road's
    slope; off the road the unit vector out of the raster is added. Equal to central
    differences, to ``sdf_at``'s autograd and to a MapStack's."""
    points = np.array([[-20.0, 1.0], [-20.0, -2.0], [60.0, 3.5], [-20.0, 7.0], [70.0, -8.0]])
    value, gradient = crossing.sdf_with_gradient(points)
    np.testing.assert_allclose(gradient[:3, 0], 0.0)
    np.testing.assert_allclose(gradient[:3, 1], [1.0, -1.0, 1.0])
    np.testing.assert_allclose(gradient[3:], [[-1.0, 1.0], [1.0, -1.0]])
    numeric = numeric_sdf_gradient(crossing, points)
    np.testing.assert_allclose(gradient, numeric, atol=1e-5)
    xy = torch.tensor(points, requires_grad=True)
    (grad,) = torch.autograd.grad(crossing.sdf_at(xy).sum(), xy)
    np.testing.assert_allclose(grad.numpy(), gradient, rtol=0, atol=1e-12)
    stacked = MapStack([crossing]).select(np.zeros(len(points), dtype=np.int64))
    stack_value, stack_gradient = stacked.sdf_with_gradient(points[:, None])
    np.testing.assert_array_equal(stack_value[:, 0], value)
    np.testing.assert_array_equal(stack_gradient[:, 0], gradient)


def test_crops_beyond_the_border_replicate_it(crossing: DrivableMap) -> None:
    """A crop past the raster's end shows the road going on, the same as one inside."""
    yaw = np.zeros(2)
    xy = np.array([[20.0, 0.0], [70.0, 0.0]])  # mid-map, and 30 m beyond its end
    drivable = crossing.crop(xy, yaw, size=32, resolution=0.5)
    np.testing.assert_array_equal(drivable[1], drivable[0])
    rows = (np.arange(32) - 15.5) * 0.5  # [m] left of the agent
    np.testing.assert_array_equal(drivable[1][:, 0], np.abs(rows) < HALF_ROAD)
    sdf = crossing.crop(xy, yaw, size=32, resolution=0.5, layer="sdf")
    np.testing.assert_array_equal(sdf[1] <= 0, drivable[1] > 0.5)
    np.testing.assert_allclose(sdf[1][drivable[1] > 0.5], sdf[0][drivable[0] > 0.5])


def test_from_lanes_opens_the_ends_on_the_edge_and_keeps_dead_ends() -> None:
    """Two lanes leave the map at both ends; a spur ends mid-map beside them, closed."""
    through = Lane(np.array([[0.0, 0.0], [100.0, 0.0]]), 4.0, "through")
    back = Lane(np.array([[100.0, 4.0], [0.0, 4.0]]), 4.0, "back")
    spur = Lane(np.array([[30.0, -2.0], [50.0, -20.0], [70.0, -20.0]]), 4.0, "spur")
    road = from_lanes((through, back, spur), resolution=RES, margin=5.0)
    xmin, ymin, xmax, _ = road.bounds
    assert (xmin, xmax) == (-5.0, 105.0) and ymin < -22.0
    beyond = np.array([[-3.0, 0.0], [-40.0, 4.0], [103.0, 4.0], [160.0, 0.0]])
    assert road.is_drivable(beyond).all()
    assert not road.is_drivable(np.array([[-40.0, 9.0], [160.0, -6.0]])).any()
    # the spur's end (x = 70) is 35 m from the border: a dead end, off-road past it
    assert not road.is_drivable(np.array([[72.0, -20.0], [80.0, -20.0]])).any()


def test_from_polygons_draws_only_continuations_that_leave_the_raster() -> None:
    road = shapely.box(0.0, -4.0, 50.0, 4.0)
    out = shapely.box(50.0, -4.0, 80.0, 4.0)  # past the raster's end at x = 55
    short = shapely.box(-3.0, 5.0, 0.0, 7.0)  # stays within the raster
    built = from_polygons(road, resolution=RES, margin=5.0, continuations=[out, short])
    plain = from_polygons(road, resolution=RES, margin=5.0)
    assert built.shape == plain.shape and built.bounds == plain.bounds
    assert built.is_drivable(np.array([[53.0, 0.0], [90.0, 0.0]])).all()
    assert not built.is_drivable(np.array([[-3.0, 0.0], [-1.5, 6.0]])).any()
    with pytest.raises(ValueError, match=r"continuations\[0\] must be a shapely Polygon"):
        from_polygons(road, continuations=[shapely.Point(0, 0)])
