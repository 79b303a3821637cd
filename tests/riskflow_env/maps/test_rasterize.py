"""Scanline polygon fill against shapely's point-in-polygon test."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from riskflow_env.maps.rasterize import fill_polygons, grid_for_bounds, pixel_centres, rasterize


def _reference(geometry, origin, shape, resolution):
    x, y = pixel_centres(origin, shape, resolution)
    return shapely.intersects_xy(geometry, x, y)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("resolution", [0.5, 0.37, 0.25])
def test_fill_matches_point_in_polygon(seed, resolution):
    rng = np.random.default_rng(seed)
    parts = [shapely.Point(rng.uniform(0, 80, 2)).buffer(rng.uniform(2, 15)) for _ in range(20)]
    parts.append(shapely.Polygon([(0, 0), (50, 20.3), (20.1, 70)]))
    parts.append(shapely.box(10.1, 10.1, 60.1, 13.4).difference(shapely.box(30.1, 11, 31.1, 12)))
    union = shapely.union_all(parts)  # holes, touching and separate parts
    origin, shape = grid_for_bounds(union.bounds, resolution, 5.0)
    expected = _reference(union, origin, shape, resolution)
    np.testing.assert_array_equal(fill_polygons(union, origin, shape, resolution), expected)
    np.testing.assert_array_equal(rasterize(union, origin, shape, resolution), expected)


def test_overlapping_parts_are_unioned_first():
    overlapping = shapely.MultiPolygon(
        [shapely.box(0.1, 0.1, 10.1, 10.1), shapely.box(5.1, 5.1, 15.1, 15.1)]
    )
    assert not overlapping.is_valid  # even-odd alone would leave the overlap empty
    origin, shape = grid_for_bounds(overlapping.bounds, 0.5, 1.0)
    union = shapely.union_all(overlapping.geoms)
    np.testing.assert_array_equal(
        rasterize(overlapping, origin, shape, 0.5), _reference(union, origin, shape, 0.5)
    )


def test_geometry_partly_outside_the_raster():
    square = shapely.box(-10.1, -10.1, 10.1, 10.1)
    origin, shape = np.array([0.0, 0.0]), (8, 6)
    np.testing.assert_array_equal(
        fill_polygons(square, origin, shape, 1.0), _reference(square, origin, shape, 1.0)
    )


@pytest.mark.parametrize("seed", range(3))
def test_overlapping_polygons_fill_to_their_union_without_one(seed):
    """Nonzero winding: overlapping parts, either orientation, holes, a shared edge."""
    rng = np.random.default_rng(seed)
    parts = [shapely.Point(rng.uniform(0, 60, 2)).buffer(rng.uniform(3, 12)) for _ in range(15)]
    parts.append(shapely.box(0.3, 0.3, 30.3, 30.3).difference(shapely.box(10.3, 10.3, 20.3, 20.3)))
    parts.append(shapely.box(30.3, 0.3, 40.3, 30.3))  # shares an edge with the last one
    parts.append(shapely.Polygon([(5, 5), (5, 25), (25, 25)]))  # clockwise, in the hole
    union = shapely.union_all(parts)
    origin, shape = grid_for_bounds(union.bounds, 0.5, 2.0)
    expected = _reference(union, origin, shape, 0.5)
    np.testing.assert_array_equal(fill_polygons(parts, origin, shape, 0.5), expected)


def test_fill_refuses_more_crossings_than_its_budget(monkeypatch):
    from riskflow_env.maps import rasterize as module

    monkeypatch.setattr(module, "MAX_FILL_CROSSINGS", 100)
    square = shapely.box(0.0, 0.0, 100.0, 100.0)  # two edges x 200 rows
    origin, shape = grid_for_bounds(square.bounds, 0.5, 1.0)
    with pytest.raises(ValueError, match="MAX_FILL_CROSSINGS"):
        fill_polygons([square], origin, shape, 0.5)


def test_the_fill_is_the_same_in_small_pieces(monkeypatch):
    """Edges cut into pieces of a few rows, in groups of a few crossings: the same raster."""
    from riskflow_env.maps import rasterize as module

    rng = np.random.default_rng(4)
    parts = [shapely.Point(rng.uniform(0, 40, 2)).buffer(rng.uniform(2, 9)) for _ in range(6)]
    parts.append(shapely.box(0.3, 0.3, 1.3, 45.3))  # a tall thin one: long edges
    origin, shape = grid_for_bounds(shapely.total_bounds(parts), 0.5, 1.0)
    whole = fill_polygons(parts, origin, shape, 0.5)
    monkeypatch.setattr(module, "_FILL_CHUNK", 7)
    np.testing.assert_array_equal(fill_polygons(parts, origin, shape, 0.5), whole)
    np.testing.assert_array_equal(whole, _reference(shapely.union_all(parts), origin, shape, 0.5))
