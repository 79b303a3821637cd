"""The drivable raster of a map as polygons, for formats that store shapes, not pixels.

:func:`drivable_outline` traces the raster exactly (the union of its drivable pixels'
squares, one box per run of drivable pixels in a row), then drops the staircase vertices
that a tolerance below half a pixel allows: every pixel centre stays on its side of the
outline (a centre lies half a pixel from the nearest pixel edge), so rasterising the
outline on the map's own grid gives back the same pixels.
"""

from __future__ import annotations

import numpy as np
import shapely

from riskflow_env.maps import DrivableMap

SIMPLIFY_PIXELS = 0.4  # [px] largest distance the simplified outline moves from the pixel edges


def drivable_outline(drivable_map: DrivableMap) -> shapely.MultiPolygon:
    """The drivable area of ``drivable_map`` as polygons [m] (with holes where the raster
    has off-road islands)."""
    grid = np.asarray(drivable_map.drivable, dtype=np.int8)
    resolution = float(drivable_map.resolution)
    ox, oy = (float(v) for v in drivable_map.origin)
    edges = np.diff(np.pad(grid, ((0, 0), (1, 1))), axis=1)
    rows, start = np.nonzero(edges == 1)  # row-major: the runs of each row in order
    _, stop = np.nonzero(edges == -1)
    boxes = shapely.box(
        ox + start * resolution,
        oy + rows * resolution,
        ox + stop * resolution,
        oy + (rows + 1) * resolution,
    )
    area = shapely.union_all(boxes)
    area = shapely.simplify(area, SIMPLIFY_PIXELS * resolution, preserve_topology=True)
    parts = [p for p in shapely.get_parts(area) if isinstance(p, shapely.Polygon) and p.area > 0]
    return shapely.MultiPolygon(parts)


def outline_rings(drivable_map: DrivableMap) -> list[np.ndarray]:
    """Every ring of :func:`drivable_outline` (outer boundaries and holes) as a closed
    (K, 2) [m] polyline, its first point repeated at the end."""
    rings = []
    for polygon in drivable_outline(drivable_map).geoms:
        for ring in (polygon.exterior, *polygon.interiors):
            rings.append(np.asarray(ring.coords, dtype=np.float64)[:, :2])
    return rings


__all__ = ["SIMPLIFY_PIXELS", "drivable_outline", "outline_rings"]
