"""Scanline polygon fill against shapely's point-in-polygon test."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from riskflow_env.maps.rasterize import fill_rings, grid_for_bounds, pixel_centres, rasterize


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
    np.testing.assert_array_equal(fill_rings(union, origin, shape, resolution), expected)
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
        fill_rings(square, origin, shape, 1.0), _reference(square, origin, shape, 1.0)
    )
