"""MapStack: several maps' SDF lookups in one call equal each map's own, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
import torch

from riskflow_env.maps import Lane, MapStack, from_lanes, from_polygons


def _maps():
    straight = from_lanes([Lane(np.array([[-50.0, 0.0], [80.0, 0.0]]), 8.0, "a")], resolution=0.5)
    diagonal = from_lanes([Lane(np.array([[0.0, 0.0], [60.0, 40.0]]), 6.0, "b")], resolution=0.25)
    square = from_polygons(shapely.box(10.0, 10.0, 40.0, 30.0), resolution=1.0)
    return [straight, diagonal, square]


def _queries(maps, generator, shape=(5, 3)) -> np.ndarray:
    """Points around each map, some beyond its raster: (M, *shape, 2) [m]."""
    points = []
    for drivable_map in maps:
        low, high = np.array(drivable_map.bounds[:2]), np.array(drivable_map.bounds[2:])
        points.append(low - 5.0 + (high - low + 10.0) * generator.random((*shape, 2)))
    return np.stack(points)


@pytest.mark.parametrize("backend", ["numpy", "float32", "float64"])
def test_lookups_equal_each_maps_own(backend):
    maps = _maps()
    stack = MapStack(maps)
    xy = _queries(maps, np.random.default_rng(0))
    index = np.arange(len(maps))
    if backend != "numpy":
        xy = torch.as_tensor(xy, dtype=getattr(torch, backend))
        index = torch.as_tensor(index)
    selection = stack.select(index)
    values, gradient = selection.sdf_with_gradient(xy)
    for m, drivable_map in enumerate(maps):
        own, own_gradient = drivable_map.sdf_with_gradient(xy[m])
        assert (values[m] == own).all() and (gradient[m] == own_gradient).all()
        assert (selection.sdf_at(xy)[m] == drivable_map.sdf_at(xy[m])).all()


def test_view_reorders_and_repeats_maps_without_copying():
    maps = _maps()
    stack = MapStack(maps)
    view = stack.view([2, 0, 2])
    assert view.maps == (maps[2], maps[0], maps[2])
    assert view._flat is stack._flat
    xy = torch.as_tensor(_queries(view.maps, np.random.default_rng(1)))
    values = view.select(torch.arange(3)).sdf_at(xy)
    for row, drivable_map in enumerate(view.maps):
        assert torch.equal(values[row], drivable_map.sdf_at(xy[row]))
    nested = view.view([1])  # map 0 of the base
    assert nested.maps == (maps[0],)
    assert torch.equal(nested.select(torch.tensor([0])).sdf_at(xy[1:2]), maps[0].sdf_at(xy[1:2]))


def test_bad_input():
    with pytest.raises(ValueError, match="maps"):
        MapStack([])
    stack = MapStack(_maps())
    with pytest.raises(ValueError, match="indices"):
        stack.view([3])
    with pytest.raises(ValueError, match="map index"):
        stack.select(np.array([0, 3]))
