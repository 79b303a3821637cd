"""DrivableMap: SDF against closed-form distances, numpy == torch, gradients, crops, errors."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import shapely
import torch

from riskflow_env.maps import DrivableMap, Lane, from_lanes, from_polygons
from tests.riskflow_env.maps.sdf_checks import numeric_sdf_gradient

RES = 0.5  # [m/px]
WIDTH, HEIGHT = 20.0, 10.0  # [m] rectangle road [0, 20] x [0, 10]


@pytest.fixture(scope="module")
def rect_map() -> DrivableMap:
    return from_polygons(shapely.box(0.0, 0.0, WIDTH, HEIGHT), resolution=RES, margin=5.0)


def rect_sdf(xy: np.ndarray) -> np.ndarray:
    """Closed-form signed distance [m] to the rectangle [0, 20] x [0, 10]."""
    dx = np.maximum(-xy[..., 0], xy[..., 0] - WIDTH)
    dy = np.maximum(-xy[..., 1], xy[..., 1] - HEIGHT)
    outside = np.hypot(np.maximum(dx, 0.0), np.maximum(dy, 0.0))
    return np.where((dx <= 0) & (dy <= 0), np.maximum(dx, dy), outside)


def test_raster_layout(rect_map: DrivableMap) -> None:
    assert rect_map.shape == (40, 60)  # rows follow y, columns follow x
    assert rect_map.bounds == pytest.approx((-5.0, -5.0, 20.0 + 5.0, 10.0 + 5.0))
    assert rect_map.extent == rect_map.bounds
    assert rect_map.drivable[10:30, 10:50].all() and rect_map.drivable.sum() == 20 * 40
    assert rect_map.sdf.dtype == np.float32
    with pytest.raises(ValueError, match="read-only"):
        rect_map.sdf[0, 0] = 1.0


def test_sdf_matches_closed_form(rect_map: DrivableMap) -> None:
    rng = np.random.default_rng(0)
    points = rng.uniform(rect_map.bounds[:2], rect_map.bounds[2:], size=(4000, 2))
    error = rect_map.sdf_at(points) - rect_sdf(points)
    assert np.abs(error).max() <= RES / 2  # half a pixel: bilinear rounds the medial ridge
    inside = rect_sdf(points) < -RES
    outside = rect_sdf(points) > RES
    assert rect_map.is_drivable(points)[inside].all()
    assert not rect_map.is_drivable(points)[outside].any()
    # the boundary is aligned with pixel edges here, so straight edges are exact
    np.testing.assert_allclose(rect_map.sdf_at(np.array([[10.0, 2.0], [10.0, -3.0]])), [-2, 3])


def test_sdf_of_rotated_polygon_within_a_pixel() -> None:
    polygon = shapely.affinity.rotate(shapely.box(0, 0, 30, 8), 27.0, origin=(0, 0))
    road = from_polygons(polygon, resolution=RES)
    rng = np.random.default_rng(1)
    points = rng.uniform(road.bounds[:2], road.bounds[2:], size=(3000, 2))
    boundary = shapely.distance(polygon.exterior, shapely.points(points))
    truth = np.where(shapely.contains_xy(polygon, points[:, 0], points[:, 1]), -boundary, boundary)
    assert np.abs(road.sdf_at(points) - truth).max() <= RES


def test_sdf_keeps_growing_off_the_raster(rect_map: DrivableMap) -> None:
    far = np.array([[-100.0, 5.0], [10.0, 80.0], [200.0, 2.0]])  # straight out of a side
    np.testing.assert_allclose(rect_map.sdf_at(far), rect_sdf(far), atol=1e-9)
    rng = np.random.default_rng(5)
    points = rng.uniform([-60.0, -60.0], [80.0, 70.0], size=(4000, 2))
    xmin, ymin, xmax, ymax = rect_map.bounds
    off = (
        (points[:, 0] < xmin)
        | (points[:, 0] > xmax)
        | (points[:, 1] < ymin)
        | (points[:, 1] > ymax)
    )
    value = rect_map.sdf_at(points[off])
    # border value + distance to the border: an upper bound of the distance, never below it
    assert (value >= rect_sdf(points[off]) - RES / 2).all()
    assert not rect_map.is_drivable(points[off]).any()


def test_numpy_and_torch_agree(rect_map: DrivableMap) -> None:
    rng = np.random.default_rng(2)
    points = rng.uniform([-12.0, -12.0], [32.0, 22.0], size=(7, 50, 2))
    expected = rect_map.sdf_at(points)
    got = rect_map.sdf_at(torch.as_tensor(points))
    assert got.shape == (7, 50) and got.dtype == torch.float64
    np.testing.assert_allclose(got.numpy(), expected, rtol=0, atol=1e-9)
    got32 = rect_map.sdf_at(torch.as_tensor(points, dtype=torch.float32))
    np.testing.assert_allclose(got32.numpy(), expected, atol=1e-4)
    assert rect_map.sdf_at(torch.as_tensor(points)).shape == (7, 50)
    assert ("sdf", "cpu", torch.float64) in rect_map._tables  # device copy kept


def test_torch_gradient_matches_finite_differences(rect_map: DrivableMap) -> None:
    rng = np.random.default_rng(3)
    points = rng.uniform([-12.0, -12.0], [32.0, 22.0], size=(200, 2))
    xy = torch.tensor(points, requires_grad=True)
    rect_map.sdf_at(xy).sum().backward()
    numeric = numeric_sdf_gradient(rect_map, points)
    np.testing.assert_allclose(xy.grad.numpy(), numeric, atol=1e-5)
    assert torch.isfinite(xy.grad).all()


def test_gradient_points_away_from_the_road(rect_map: DrivableMap) -> None:
    rng = np.random.default_rng(4)
    points = rng.uniform([-40.0, -40.0], [60.0, 50.0], size=(2000, 2))
    points = points[rect_sdf(points) > 1.5]  # clearly off-road, on or beyond the raster
    xy = torch.tensor(points, requires_grad=True)
    rect_map.sdf_at(xy).sum().backward()
    nearest = np.clip(points, [0.0, 0.0], [WIDTH, HEIGHT])
    away = (points - nearest) / np.linalg.norm(points - nearest, axis=1, keepdims=True)
    assert (np.sum(xy.grad.numpy() * away, axis=1) > 0.5).all()


def _blob_map(centre: tuple[float, float]) -> DrivableMap:
    """A 4 m square of road centred at ``centre``: an off-centre feature for crops."""
    x, y = centre
    return from_polygons(shapely.box(x - 2, y - 2, x + 2, y + 2), resolution=0.25, margin=20.0)


def _centroid(image: np.ndarray) -> np.ndarray:
    rows, cols = np.indices(image.shape)
    return np.array([(rows * image).sum(), (cols * image).sum()]) / image.sum()


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_crop_orientation(backend: str) -> None:
    size = 129  # [px] of 0.25 m: centre pixel 64, a 10 m offset is 40 px
    east, north = _blob_map((10.0, 0.0)), _blob_map((0.0, 10.0))
    xy = np.zeros((2, 2))
    yaw = np.array([0.0, np.pi / 2])
    if backend == "torch":
        xy, yaw = torch.as_tensor(xy), torch.as_tensor(yaw)
    crops = {name: road.crop(xy, yaw, size=size) for name, road in [("e", east), ("n", north)]}
    crops = {k: np.asarray(v) for k, v in crops.items()}
    # heading 0: east is straight ahead (columns up), north is to the left (rows up)
    np.testing.assert_allclose(_centroid(crops["e"][0]), [64, 104], atol=1e-6)
    np.testing.assert_allclose(_centroid(crops["n"][0]), [104, 64], atol=1e-6)
    # heading pi/2 (facing north): north is ahead, east is to the right (rows down)
    np.testing.assert_allclose(_centroid(crops["n"][1]), [64, 104], atol=1e-6)
    np.testing.assert_allclose(_centroid(crops["e"][1]), [24, 64], atol=1e-6)
    assert crops["e"].max() == pytest.approx(1.0) and crops["e"].min() == 0.0
    assert crops["e"][0].sum() == pytest.approx(16 * 16)  # the 4 m square is 16 x 16 px
    coarse = east.crop(np.zeros((1, 2)), np.zeros(1), size=49, resolution=0.5)[0]
    np.testing.assert_allclose(_centroid(coarse), [24, 44], atol=1e-6)  # 10 m = 20 px


def test_crop_sdf_layer_and_backends(rect_map: DrivableMap) -> None:
    xy = np.array([[10.0, 5.0], [18.0, 1.0], [-3.0, 12.0]])
    yaw = np.array([0.3, -2.0, 3.0])
    crops = rect_map.crop(xy, yaw, size=9, layer="sdf")
    assert crops.shape == (3, 9, 9)
    np.testing.assert_allclose(crops[:, 4, 4], rect_map.sdf_at(xy), atol=1e-6)  # agent at centre
    torch_crops = rect_map.crop(torch.as_tensor(xy), torch.as_tensor(yaw), size=9, layer="sdf")
    np.testing.assert_allclose(torch_crops.numpy(), crops, atol=1e-9)
    drivable = rect_map.crop(xy, yaw, size=5, resolution=1.0)  # +-2 m around the agent
    assert drivable[0].min() == 1.0 and drivable[2].max() == 0.0


def test_nearest_lane_and_lane_by_id() -> None:
    lanes = (
        Lane(np.array([[0.0, 0.0], [50.0, 0.0]]), 4.0, "a->b#0", 30.0, ("b->c#0",)),
        Lane(np.array([[0.0, 4.0], [50.0, 4.0]]), 4.0, "a->b#1", 30.0),
    )
    road = from_lanes(lanes, resolution=0.5, margin=2.0, name="two lanes")
    assert road.lane_by_id("a->b#1") is lanes[1]
    with pytest.raises(KeyError, match="a->b#0, a->b#1"):
        road.lane_by_id("nope")
    index, s, lateral = road.nearest_lane(np.array([[10.0, 0.5], [20.0, 3.0], [60.0, 5.0]]))
    np.testing.assert_array_equal(index, [0, 1, 1])
    np.testing.assert_allclose(s, [10.0, 20.0, 50.0])
    np.testing.assert_allclose(lateral, [0.5, -1.0, np.hypot(10.0, 1.0)])
    index_t, s_t, _ = road.nearest_lane(torch.tensor([[10.0, 0.5]]))
    assert index_t.tolist() == [0] and s_t.tolist() == [10.0]
    # the ends lie on the map's edge: the road leaves it there, going on at its width
    assert road.is_drivable(
        np.array([[0.25, -1.9], [49.75, 5.9], [-0.75, 0.0], [50.75, 4.0]])
    ).all()
    assert not road.is_drivable(np.array([[-0.75, -2.25], [50.75, 6.25]])).any()
    assert "two lanes" in repr(road)


def test_pickle_round_trip(rect_map: DrivableMap) -> None:
    rect_map.sdf_at(torch.zeros(2))  # fill the torch cache
    clone = pickle.loads(pickle.dumps(rect_map))
    np.testing.assert_array_equal(clone.sdf, rect_map.sdf)
    assert clone._tables == {}


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"drivable": np.ones((4, 4))}, "drivable must be a 2-D bool"),
        ({"drivable": np.ones(4, dtype=bool)}, "drivable must be a 2-D bool"),
        ({"drivable": np.ones((1, 4), dtype=bool)}, "H, W >= 2"),
        ({"drivable": np.zeros((4, 4), dtype=bool)}, "no drivable"),
        ({"resolution": 0.0}, "resolution"),
        ({"resolution": float("nan")}, "resolution"),
        ({"resolution": "0.5"}, "resolution"),
        ({"origin": np.zeros(3)}, "origin"),
        ({"sdf": np.zeros((3, 3))}, "sdf must have"),
        ({"sdf": -np.ones((4, 4))}, "sdf must be <= 0 exactly where"),
        ({"lanes": (Lane([[0, 0], [1, 0]], 1.0, "x"),) * 2}, "unique lane_id"),
        ({"lanes": ("x",)}, "Lane objects"),
    ],
)
def test_map_rejects_bad_input(kwargs: dict, match: str) -> None:
    drivable = np.zeros((4, 4), dtype=bool)
    drivable[1:3, 1:3] = True
    args = {"drivable": drivable, "resolution": 1.0, "origin": np.zeros(2)} | kwargs
    with pytest.raises(ValueError, match=match):
        DrivableMap(**args)


def test_lookups_and_builders_reject_bad_input(rect_map: DrivableMap) -> None:
    with pytest.raises(ValueError, match=r"xy must have shape \(\.\.\., 2\)"):
        rect_map.sdf_at(np.zeros((5, 3)))
    with pytest.raises(ValueError, match="crop needs xy"):
        rect_map.crop(np.zeros((3, 2)), np.zeros(2))
    with pytest.raises(ValueError, match="crop size"):
        rect_map.crop(np.zeros((1, 2)), np.zeros(1), size=0)
    with pytest.raises(ValueError, match="crop resolution"):
        rect_map.crop(np.zeros((1, 2)), np.zeros(1), resolution=-1.0)
    with pytest.raises(ValueError, match="crop layer"):
        rect_map.crop(np.zeros((1, 2)), np.zeros(1), layer="lanes")
    with pytest.raises(ValueError, match="has no lanes"):
        rect_map.nearest_lane(np.zeros(2))
    with pytest.raises(ValueError, match=r"polygons\[1\] must be a shapely Polygon"):
        from_polygons([shapely.box(0, 0, 1, 1), shapely.Point(0, 0)])
    with pytest.raises(ValueError, match="non-empty area"):
        from_polygons([])
    with pytest.raises(ValueError, match="margin"):
        from_polygons(shapely.box(0, 0, 1, 1), margin=-1.0)
    with pytest.raises(ValueError, match="thinner than the resolution"):
        from_polygons(shapely.box(0, 0, 0.1, 0.1), resolution=1.0, margin=0.0)
    with pytest.raises(ValueError, match="MAX_PIXELS"):
        from_polygons(shapely.box(0, 0, 1e5, 1e5), resolution=0.5)
    with pytest.raises(ValueError, match="at least one Lane"):
        from_lanes([])


def test_sdf_with_gradient_matches_finite_differences_numpy_and_torch(
    rect_map: DrivableMap,
) -> None:
    """The analytic gradient (on and beyond the raster) against central differences,
    the same in numpy and torch; its values are ``sdf_at``'s, bit for bit."""
    rng = np.random.default_rng(5)
    points = rng.uniform([-12.0, -12.0], [32.0, 22.0], size=(300, 2))
    value, gradient = rect_map.sdf_with_gradient(points)
    np.testing.assert_array_equal(value, rect_map.sdf_at(points))
    numeric = numeric_sdf_gradient(rect_map, points)
    np.testing.assert_allclose(gradient, numeric, atol=1e-5)
    value_t, gradient_t = rect_map.sdf_with_gradient(torch.as_tensor(points))
    # numpy and torch evaluate the bilinear lookup with their own kernels: float64 values of
    # tens of metres differ by a few ulps (1.8e-15 seen), far below 1e-12 m.
    np.testing.assert_allclose(value_t.numpy(), value, rtol=0, atol=1e-12)
    np.testing.assert_allclose(gradient_t.numpy(), gradient, rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_autograd_through_sdf_at_is_the_analytic_gradient(
    rect_map: DrivableMap, dtype: torch.dtype
) -> None:
    """A query that requires grad gets the same values as one that does not and, as its
    autograd gradient, ``sdf_with_gradient``'s."""
    rng = np.random.default_rng(6)
    points = torch.as_tensor(
        rng.uniform([-12.0, -12.0], [32.0, 22.0], size=(4, 50, 2)), dtype=dtype
    )
    xy = points.clone().requires_grad_(True)
    value = rect_map.sdf_at(xy)
    (grad,) = torch.autograd.grad(value.sum(), xy)
    expected_value, expected_grad = rect_map.sdf_with_gradient(points)
    assert torch.equal(value.detach(), expected_value)
    assert torch.equal(value.detach(), rect_map.sdf_at(points))
    assert torch.equal(grad, expected_grad)


@pytest.mark.parametrize("layer", ["drivable", "sdf"])
@pytest.mark.parametrize(("size", "resolution"), [(48, 1.0), (17, 0.3), (1, None)])
def test_compiled_crop_gives_numpys_float32_values(layer, size, resolution, monkeypatch):
    """float32 queries (the learned policies' windows) run riskflow_env.maps.crop_kernels:
    the same values bit for bit, on and far off the raster."""
    pytest.importorskip("numba")
    from riskflow_env.compiled import SWITCH
    from riskflow_env.scenarios import shipped_bank

    scenario = shipped_bank("eval")[2]
    rng = np.random.default_rng(size)
    xy = scenario.states[0, scenario.current_index, :2] + rng.normal(0.0, 40.0, (32, 2))
    yaw = rng.uniform(-4.0, 4.0, 32)
    crops = {}
    for switch in ("0", "1"):
        monkeypatch.setenv(SWITCH, switch)
        crops[switch] = scenario.map.crop(
            xy.astype(np.float32), yaw.astype(np.float32), size, resolution, layer
        )
    assert crops["1"].dtype == crops["0"].dtype == np.float32
    assert crops["1"].shape == (32, size, size)
    np.testing.assert_array_equal(crops["1"], crops["0"])
