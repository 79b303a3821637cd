"""Bilinear raster lookups and agent-centred crop grids, one implementation for numpy and torch.

The functions take the raster ("table") already in the query's backend, dtype and
device; :class:`~riskflow_env.maps.DrivableMap` keeps those copies.
"""

from __future__ import annotations

import numpy as np

from riskflow_env._array import (
    Array,
    asarray_like,
    attach_gradient,
    detach,
    is_torch,
    namespace,
    requires_grad,
    take,
)


def bilinear(
    table: Array, xy: Array, origin: tuple[float, float], resolution: float, extend: bool
) -> Array:
    """Bilinear interpolation of ``table`` over pixel centres at world points ``xy``.

    Args:
        table: (H, W) values at pixel centres, same backend/dtype as ``xy``; H, W >= 2.
        xy: (..., 2) [m] world points (differentiable in torch).
        origin: (x, y) [m] lower-left corner of pixel [0, 0].
        resolution: pixel size [m/px].
        extend: beyond the outermost pixel centres the query is clamped onto them (the
            border pixels continue outward); with ``extend`` (a signed distance field)
            the distance [m] from the clamped point to the query is added where the
            clamped value is positive: off-road ground beyond the border keeps growing
            away from the road, a road that crosses the border goes on straight.

    Returns:
        (...) interpolated values. A torch ``xy`` that requires grad gets the values
        with their exact first-order gradient (:func:`bilinear_with_gradient`) attached
        as one linear term (:func:`~riskflow_env._array.attach_gradient`): the same
        values and gradients as differentiating the interpolation op by op, with a
        handful of graph nodes instead of forty (the guidance loop's hot spot). Second
        derivatives are zero (they are, almost everywhere, within a cell).
    """
    if requires_grad(xy):
        value, gradient = _interpolate(table, detach(xy), origin, resolution, extend, True)
        return attach_gradient(value, xy, gradient)
    return _interpolate(table, xy, origin, resolution, extend, False)[0]


def bilinear_with_gradient(
    table: Array, xy: Array, origin: tuple[float, float], resolution: float, extend: bool
) -> tuple[Array, Array]:
    """:func:`bilinear` and its gradient with respect to ``xy``.

    Returns:
        (...) values and (..., 2) their gradient [value units / m]: within the pixel
        centres the interpolant's slope, beyond them (where the query is clamped) 0,
        plus with ``extend`` the unit vector from the clamped point to the query
        (0 on the clamped point itself). At a cell edge the slope is the cell's on the
        side of the lower index, as torch's autograd takes it.
    """
    return _interpolate(table, xy, origin, resolution, extend, True)


def _interpolate(
    table: Array,
    xy: Array,
    origin: tuple[float, float],
    resolution: float,
    extend: bool,
    with_gradient: bool,
) -> tuple[Array, Array | None]:
    """:func:`interpolate_flat` of one raster (the one implementation of :func:`bilinear`
    and :func:`bilinear_with_gradient`)."""
    xp = namespace(xy, table)
    height, width = table.shape
    grid = (height, width, origin[0], origin[1], resolution, 0)
    return interpolate_flat(xp.reshape(table, (-1,)), xy, grid, extend, with_gradient)


def interpolate_flat(
    flat: Array, xy: Array, grid: tuple, extend: bool, with_gradient: bool
) -> tuple[Array, Array | None]:
    """Bilinear lookup in rasters stored end to end in ``flat`` (the one implementation).

    Args:
        flat: (N,) values at pixel centres of one or more rasters, row-major each.
        xy: (..., 2) [m] world points, same backend/dtype as ``flat``.
        grid: ``(height, width, origin_x [m], origin_y [m], resolution [m/px], offset)``
            of the raster each point is looked up in (``offset``: index in ``flat`` of its
            pixel [0, 0]); each a Python number (every point on the same raster) or an
            array broadcastable to ``xy[..., 0]`` (a raster per point:
            :class:`~riskflow_env.maps.stack.MapStack`). Heights and widths >= 2.
        extend, with_gradient: as :func:`bilinear` / :func:`bilinear_with_gradient`.

    Returns:
        (...) values and, with ``with_gradient``, (..., 2) their gradient (else None).
    """
    xp = namespace(xy, flat)
    height, width, origin_x, origin_y, resolution, offset = grid
    col = (xy[..., 0] - origin_x) / resolution - 0.5
    row = (xy[..., 1] - origin_y) / resolution - 0.5
    last_col, last_row = _last(xp, width, col), _last(xp, height, row)
    col_c = xp.clip(col, 0.0, last_col)
    row_c = xp.clip(row, 0.0, last_row)
    # Integer bounds with maximum/minimum: the same values at a fraction of clip's cost;
    # the clamped indices are >= 0, so the cast's truncation is the floor.
    col0 = xp.maximum(xp.minimum(xp.astype(col_c, xp.int64), width - 2), 0)
    row0 = xp.maximum(xp.minimum(xp.astype(row_c, xp.int64), height - 2), 0)
    fc = col_c - xp.astype(col0, col_c.dtype)
    fr = row_c - xp.astype(row0, row_c.dtype)
    base = row0 * width + col0 + offset
    if isinstance(width, (int, np.integer)):  # one gather of the four corners
        steps = asarray_like(np.array([0, 1, width, width + 1]), base)
        gathered = take(flat, base[..., None] + steps)  # (..., 4)
        corners = tuple(gathered[..., k] for k in range(4))
    else:  # a raster per point (MapStack)
        below = base + width
        corners = (take(flat, base), take(flat, base + 1), take(flat, below), take(flat, below + 1))
    if flat.dtype != fc.dtype:
        # A float32 raster queried in float64: cast the four corners once (exactly as the
        # promotion would) rather than inside every mixed-type op.
        corners = tuple(xp.astype(value, xp.result_type(value, fc)) for value in corners)
    v00, v01, v10, v11 = corners
    gc, gr = 1 - fc, 1 - fr
    top = v00 * gc + v01 * fc
    bottom = v10 * gc + v11 * fc
    value = top * gr + bottom * fr
    if extend:
        off_c, off_r = col - col_c, row - row_c  # [px] from the clamped point to the query
        # safe_norm's guard is for autograd only; a query without it takes the plain root
        squared = off_c * off_c + off_r * off_r
        distance = safe_norm(xp, off_c, off_r) if requires_grad(xy) else xp.sqrt(squared)
        distance = xp.where(value > 0, distance, xp.zeros_like(distance))
        value = value + distance * resolution
    if not with_gradient:
        return value, None
    # d value / d (col, row) inside the clamp (torch's clamp passes the gradient on the
    # bounds too: inside means the clamp left the index as it was), then / resolution.
    inside_c = xp.astype(col == col_c, value.dtype)
    inside_r = xp.astype(row == row_c, value.dtype)
    d_col = ((v01 - v00) * gr + (v11 - v10) * fr) * (inside_c / resolution)
    d_row = (bottom - top) * (inside_r / resolution)
    if extend:  # d(|q - clamp(q)| * resolution) / dxy: the unit vector off the raster
        # on the raster, or where the value is not positive, the distance is 0 (so are
        # the offsets on the raster; beyond it the distance is 0 only for a value <= 0)
        grow = distance > 0
        distance = xp.where(grow, distance, xp.ones_like(distance))
        zero = xp.zeros_like(distance)
        d_col = d_col + xp.where(grow, off_c / distance, zero)
        d_row = d_row + xp.where(grow, off_r / distance, zero)
    return value, xp.stack([d_col, d_row], axis=-1)


def _last(xp, size: int | Array, like: Array) -> float | Array:
    """Index of the last pixel centre, ``size - 1``: a float, or an array of ``like``'s dtype."""
    if isinstance(size, (int, np.integer)):
        return float(size - 1)
    return xp.astype(size - 1, like.dtype)


def crop_offsets(size: int, resolution: float) -> np.ndarray:
    """(size,) [m] float64 offsets of a crop's pixel centres from its centre, along the
    columns (forward) and the rows (left) alike (:func:`crop_points`)."""
    return (np.arange(size, dtype=np.float64) - (size - 1) / 2.0) * resolution


def crop_points(xy: Array, yaw: Array, size: int, resolution: float) -> Array:
    """World coordinates of the pixel centres of agent-centred, heading-aligned crops.

    Crop pixel (r, c) sits at forward offset ``(c - (size-1)/2) * resolution`` and
    leftward offset ``(r - (size-1)/2) * resolution`` from the agent: the agent is at
    the crop centre, columns increase along the heading, rows increase to its left
    (so a crop shown with the row axis pointing up is the agent's view, nose right).

    Args:
        xy: (N, 2) [m] agent positions.
        yaw: (N,) [rad] agent headings.
        size: crop side [px].
        resolution: crop pixel size [m/px].

    Returns:
        (N, size, size, 2) [m] world points.
    """
    xp = namespace(xy, yaw)
    offsets = asarray_like(crop_offsets(size, resolution), xy)
    forward = offsets[None, None, :]  # varies along columns
    left = offsets[None, :, None]  # varies along rows
    cos = xp.cos(yaw)[:, None, None]
    sin = xp.sin(yaw)[:, None, None]
    x = xy[:, 0, None, None] + forward * cos - left * sin
    y = xy[:, 1, None, None] + forward * sin + left * cos
    return xp.stack([x, y], axis=-1)


def safe_norm(xp, dx: Array, dy: Array) -> Array:
    """sqrt(dx^2 + dy^2) with a zero (not NaN) gradient at the origin.

    The guard only matters for gradients: numpy arrays take the plain square root
    (the same values, without the two ``where`` passes).
    """
    sq = dx * dx + dy * dy
    if isinstance(sq, np.ndarray):
        return np.sqrt(sq)
    positive = sq > 0
    return xp.where(positive, xp.sqrt(xp.where(positive, sq, xp.ones_like(sq))), xp.zeros_like(sq))


def constant_like(array: np.ndarray, like: Array) -> Array:
    """Read-only numpy constant ``array`` in ``like``'s backend, dtype and device.

    Torch gets a copy (torch does not share read-only numpy memory).
    """
    return asarray_like(np.array(array) if is_torch(like) else array, like)
