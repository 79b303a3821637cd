"""Geometry -> raster: the pixel grid, polygon rasterisation and the signed distance field.

Grid convention (shared with :class:`~riskflow_env.maps.DrivableMap`): ``origin`` is
the world (x, y) of the lower-left corner of pixel [0, 0]; row ``i`` covers
y in [oy + i*res, oy + (i+1)*res) and column ``j`` covers x in
[ox + j*res, ox + (j+1)*res). A pixel is sampled at its centre.

Budgets: a raster holds at most :data:`MAX_PIXELS` pixels (the area), a polygon fill
takes at most :data:`MAX_FILL_CROSSINGS` crossings of edges with pixel rows, and an invalid
(self-intersecting) polygon is repaired (``shapely.make_valid``) only within
:class:`RepairBudget`: GEOS's repair time grows faster than the square of the number of
crossing edges (a 101-vertex star, 2,500 crossings: 6.5 s; 201 vertices: 65 s; 501
vertices: hours), so a polygon of more than :data:`MAX_REPAIR_VERTICES` vertices or
with more than :data:`MAX_REPAIR_CROSSINGS` crossing pairs of edges is refused with a
``ValueError`` naming it, and so is a repair once its budget is spent (valid polygons
cost one ``is_valid`` check). The four nuScenes samples of ScenarioNet repair at most 37
lane surfaces a map, of at most 149 vertices and 15 crossings: 190 of the
:data:`MAX_REPAIRS` units and 5% of :data:`MAX_REPAIR_PAIRS`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import shapely
from scipy import ndimage

MAX_PIXELS = 50_000_000  # [-] largest raster a builder will allocate (H * W)
MAX_REPAIR_VERTICES = 1024  # vertices of one invalid polygon that may be repaired
MAX_REPAIR_CROSSINGS = 64  # crossing pairs of edges of one polygon that may be repaired
MAX_REPAIRS = 1024  # repairs of one budget (one map): 1 + its crossings each
MAX_REPAIR_PAIRS = 2**24  # pairs of edges one budget may test for crossings (~3 s)
MAX_FILL_CROSSINGS = 2**25  # crossings of polygon edges with pixel rows one fill may take
_CROSSING_ROWS = 64  # edges compared with all others at once (bounds the arrays)
_FILL_CHUNK = 2**20  # crossings computed at once by a fill (80-160 MB of arrays)


class RepairBudget:
    """What the repairs of one map build may still cost: ``left`` repair units (1 + the
    crossings of each repair, :data:`MAX_REPAIRS`) and ``pairs`` edge pairs tested
    (:data:`MAX_REPAIR_PAIRS`); shared by the calls of :func:`repair_polygon` for it."""

    def __init__(self) -> None:
        self.left, self.pairs = MAX_REPAIRS, MAX_REPAIR_PAIRS


def repair_polygon(
    shape: shapely.Geometry, what: str = "polygon", budget: RepairBudget | None = None
) -> shapely.Geometry:
    """``shape`` when it is valid, else ``shapely.make_valid(shape)``, within the budget
    (module docstring; None: a budget of its own).

    Raises:
        ValueError naming ``what`` when the repair is beyond the budget.
    """
    if shapely.is_valid(shape):
        return shape
    budget = RepairBudget() if budget is None else budget
    vertices = int(shapely.get_num_coordinates(shape))
    budget.pairs -= vertices * vertices // 2
    if budget.left <= 0 or budget.pairs < 0 or vertices > MAX_REPAIR_VERTICES:
        raise ValueError(
            f"{what}: a self-intersecting polygon of {vertices} vertices is refused (repaired "
            f"only up to MAX_REPAIR_VERTICES = {MAX_REPAIR_VERTICES} vertices, within "
            f"MAX_REPAIRS = {MAX_REPAIRS} and MAX_REPAIR_PAIRS = {MAX_REPAIR_PAIRS} a map)"
        )
    crossings = crossing_pairs(shape, MAX_REPAIR_CROSSINGS)
    if crossings > MAX_REPAIR_CROSSINGS:
        raise ValueError(
            f"{what}: a polygon whose edges cross more than MAX_REPAIR_CROSSINGS = "
            f"{MAX_REPAIR_CROSSINGS} times is refused (its repair would take minutes)"
        )
    budget.left -= 1 + crossings
    return shapely.make_valid(shape)


def crossing_pairs(shape: shapely.Geometry, limit: int) -> int:
    """The number of pairs of non-adjacent ring edges of ``shape`` that touch or cross,
    counted up to ``limit + 1`` (:func:`line_crossings` of its rings)."""
    rings = [
        np.asarray(ring.coords)[:, :2]
        for polygon in shapely.get_parts(shape)
        if isinstance(polygon, shapely.Polygon) and not polygon.is_empty
        for ring in (polygon.exterior, *polygon.interiors)
    ]
    return line_crossings(rings, limit, closed=True)


def line_crossings(lines: list[np.ndarray], limit: int, closed: bool = False) -> int:
    """The number of pairs of segments of ``lines`` ((K, 2) [m] each; rings when
    ``closed``) that touch or cross, leaving out consecutive segments of one line, counted
    up to ``limit + 1``: a vectorised all-pairs test, ``_CROSSING_ROWS`` segments at a
    time, so its cost is the square of the number of segments (callers bound it)."""
    lines = [line for line in lines if len(line) >= 2]
    if not lines:
        return 0
    a = np.concatenate([line[:-1] for line in lines])
    b = np.concatenate([line[1:] for line in lines])
    ring = np.repeat(np.arange(len(lines)), [len(line) - 1 for line in lines])
    count = len(a)
    position = np.arange(count)
    first = np.searchsorted(ring, ring, side="left")  # lines are contiguous
    last = np.searchsorted(ring, ring, side="right") - 1
    found = 0
    for row in range(0, count, _CROSSING_ROWS):
        i = position[row : row + _CROSSING_ROWS, None]
        j = position[None, row:]  # pairs (i, j > i) only
        adjacent = np.abs(i - j) <= 1
        if closed:  # a ring's first and last segments meet too
            adjacent |= ((i == first[i]) & (j == last[i])) | ((j == first[i]) & (i == last[i]))
        adjacent &= ring[i] == ring[j]
        pa, pb, qa, qb = a[i], b[i], a[j], b[j]
        d1, d2 = _side(pa, pb, qa), _side(pa, pb, qb)
        d3, d4 = _side(qa, qb, pa), _side(qa, qb, pb)
        meet = (d1 * d2 <= 0) & (d3 * d4 <= 0) & (j > i) & ~adjacent
        collinear = (d1 == 0) & (d2 == 0)
        apart = np.any(
            (np.maximum(pa, pb) < np.minimum(qa, qb)) | (np.maximum(qa, qb) < np.minimum(pa, pb)),
            axis=-1,
        )
        found += int(np.count_nonzero(meet & ~(collinear & apart)))
        if found > limit:
            break
    return found


def _side(origin: np.ndarray, end: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Sign of the cross product (end - origin) x (point - origin) (-1, 0, 1)."""
    u, v = end - origin, point - origin
    return np.sign(u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0])


def grid_for_bounds(
    bounds: tuple[float, float, float, float], resolution: float, margin: float
) -> tuple[np.ndarray, tuple[int, int]]:
    """Origin and shape of a raster covering ``bounds`` plus ``margin`` on every side.

    Args:
        bounds: (xmin, ymin, xmax, ymax) [m] of the geometry.
        resolution: pixel size [m/px], > 0.
        margin: free border added around ``bounds`` [m], >= 0.

    Returns:
        origin: (2,) [m] lower-left corner of pixel [0, 0].
        shape: (H, W) [px], each at least 2.
    """
    xmin, ymin, xmax, ymax = bounds
    width = max(int(math.ceil((xmax - xmin + 2.0 * margin) / resolution)), 2)
    height = max(int(math.ceil((ymax - ymin + 2.0 * margin) / resolution)), 2)
    if height * width > MAX_PIXELS:
        raise ValueError(
            f"raster of {height} x {width} px exceeds MAX_PIXELS={MAX_PIXELS}; "
            f"use a coarser resolution (got {resolution} m/px) or a smaller geometry"
        )
    return np.array([xmin - margin, ymin - margin], dtype=np.float64), (height, width)


def pixel_centres(origin: np.ndarray, shape: tuple[int, int], resolution: float) -> tuple:
    """World coordinates of all pixel centres.

    Returns:
        x, y: two (H, W) [m] arrays.
    """
    height, width = shape
    xs = origin[0] + (np.arange(width) + 0.5) * resolution
    ys = origin[1] + (np.arange(height) + 0.5) * resolution
    x, y = np.meshgrid(xs, ys)  # (H, W), rows follow y
    return x, y


def rasterize(
    geometry: shapely.Geometry, origin: np.ndarray, shape: tuple[int, int], resolution: float
) -> np.ndarray:
    """Boolean raster of the pixels whose centre lies in ``geometry``.

    Polygons are filled by scanlines (:func:`fill_polygons`, no union is computed); an
    invalid part is repaired first (:func:`repair_polygon`). A pixel centre exactly on a
    left or lower edge counts as inside, one on a right or upper edge as outside. Other
    geometries go through ``shapely.intersects_xy`` (boundary points inside).

    Returns:
        (H, W) bool.
    """
    parts = shapely.get_parts(geometry)
    if len(parts) and all(isinstance(p, shapely.Polygon) for p in parts):
        budget = RepairBudget()
        parts = [repair_polygon(part, f"polygon part {k}", budget) for k, part in enumerate(parts)]
        return fill_polygons(parts, origin, shape, resolution)
    x, y = pixel_centres(origin, shape, resolution)
    shapely.prepare(geometry)
    return np.asarray(shapely.intersects_xy(geometry, x, y), dtype=bool)


def fill_polygons(
    polygons: Sequence[shapely.Geometry],
    origin: np.ndarray,
    shape: tuple[int, int],
    resolution: float,
) -> np.ndarray:
    """(H, W) bool: the pixels whose centre lies in the union of ``polygons`` (valid
    Polygons or MultiPolygons, overlapping or not), by a nonzero-winding scanline fill.

    Every ring is taken counter-clockwise for an exterior and clockwise for a hole
    (``shapely.is_ccw``), so the winding number of a point is the number of polygons
    holding it. For each pixel row the crossings of the row's centre line with all edges
    are found at once (an edge spans the rows whose centre v satisfies
    ``min(v0, v1) <= v < max(v0, v1)``, so a shared vertex counts once); each crossing
    adds its edge's direction (+1 up, -1 down) at the first pixel whose centre lies at
    or right of it, and a running sum along the row gives the winding number. No union
    is computed, so the cost is the number of crossings plus H * W whatever the polygons'
    overlaps (a union grows as the crossings of their outlines); more than
    :data:`MAX_FILL_CROSSINGS` crossings raise ``ValueError``.
    """
    height, width = shape
    rings, exterior = [], []
    for polygon in shapely.get_parts(np.asarray(polygons, dtype=object)):
        if isinstance(polygon, shapely.Polygon) and not polygon.is_empty:
            rings += [polygon.exterior, *polygon.interiors]
            exterior += [True] + [False] * len(polygon.interiors)
    winding = np.zeros((height, width + 1), dtype=np.int32)
    if not rings:
        return winding[:, :width] != 0
    coords = [np.asarray(ring.coords)[:, :2] for ring in rings]
    start = (np.concatenate([c[:-1] for c in coords]) - origin) / resolution - 0.5
    end = (np.concatenate([c[1:] for c in coords]) - origin) / resolution - 0.5
    upright = shapely.is_ccw(np.asarray(rings, dtype=object)) == np.array(exterior)
    ring_sign = np.repeat(np.where(upright, 1, -1), [len(c) - 1 for c in coords])
    sign = np.where(end[:, 1] > start[:, 1], 1, -1) * ring_sign
    low = np.clip(np.ceil(np.minimum(start[:, 1], end[:, 1])), 0, height).astype(np.int64)
    high = np.clip(np.ceil(np.maximum(start[:, 1], end[:, 1])), 0, height).astype(np.int64)
    count = np.maximum(high - low, 0)
    total = int(count.sum())
    if total > MAX_FILL_CROSSINGS:
        raise ValueError(
            f"polygons: their edges cross {total} pixel rows, over MAX_FILL_CROSSINGS = "
            f"{MAX_FILL_CROSSINGS} (use a coarser resolution or fewer, simpler polygons)"
        )
    # pieces of at most _FILL_CHUNK rows of one edge, in groups of about _FILL_CHUNK
    # crossings (at most twice that): a group's arrays stay under ~160 MB, whatever an edge spans
    pieces = np.maximum(-(-count // _FILL_CHUNK), 1)
    piece_edge = np.repeat(np.arange(len(count)), pieces)
    first = np.repeat(np.cumsum(pieces) - pieces, pieces)
    piece_low = low[piece_edge] + (np.arange(len(piece_edge)) - first) * _FILL_CHUNK
    piece_rows = np.clip(high[piece_edge] - piece_low, 0, _FILL_CHUNK)
    groups = (np.cumsum(piece_rows) - 1) // _FILL_CHUNK
    for chosen in np.split(np.arange(len(piece_rows)), np.flatnonzero(np.diff(groups)) + 1):
        spans = piece_rows[chosen]
        edge = np.repeat(piece_edge[chosen], spans)
        row = np.repeat(piece_low[chosen] - (np.cumsum(spans) - spans), spans) + np.arange(
            len(edge)
        )
        (u0, v0), (u1, v1) = start[edge].T, end[edge].T
        u = u0 + (row - v0) / (v1 - v0) * (u1 - u0)  # v1 != v0 on every spanned row
        col = np.clip(np.ceil(u), 0, width).astype(np.int64)
        np.add.at(winding.reshape(-1), row * (width + 1) + col, sign[edge].astype(np.int32))
    return np.cumsum(winding, axis=1, dtype=np.int32)[:, :width] != 0


def signed_distance(drivable: np.ndarray, resolution: float) -> np.ndarray:
    """Signed distance [m] from each pixel centre to the drivable boundary.

    Negative inside the drivable area, positive outside. Both sides come from
    ``scipy.ndimage.distance_transform_edt`` (distance between pixel centres); the
    boundary lies half a pixel beyond the last pixel of a side, so each side's
    distance is reduced by 0.5 px. The ground beyond the raster is its border pixels
    continued outward (as the map's lookups read it), which puts no boundary nearer to
    any pixel than the raster's own: a road crossing the border has no edge there. An
    all-drivable raster has no boundary at all; its distances are the raster's size,
    ``H + W`` px.

    Args:
        drivable: (H, W) bool, at least one True pixel.
        resolution: pixel size [m/px].

    Returns:
        (H, W) float32 [m]; |value| >= resolution / 2 everywhere.
    """
    if np.all(drivable):
        return np.full(drivable.shape, -sum(drivable.shape) * resolution, dtype=np.float32)
    inside = ndimage.distance_transform_edt(drivable)
    outside = ndimage.distance_transform_edt(~drivable)
    sdf = np.where(drivable, -(inside - 0.5), outside - 0.5) * resolution
    return sdf.astype(np.float32)
