"""Lane centrelines: polylines with a width, an id, a speed limit and successors.

A :class:`Lane` is pure geometry. ``position`` (arclength -> point, heading) and
``project`` (point -> arclength, signed lateral offset) are written once against the
array API, so they run on numpy arrays and on torch tensors (differentiable wrt the
query) alike. The drivable surface of lanes is built in
:mod:`riskflow_env.maps.surface`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from riskflow_env._array import Array, is_torch, namespace
from riskflow_env.maps._validate import finite_number
from riskflow_env.maps.sampling import constant_like, safe_norm


def as_query(values: Array, name: str, last_dim: int | None = None) -> Array:
    """``values`` as a floating array (torch kept as is, anything else -> numpy).

    Args:
        values: array-like of query coordinates.
        name: argument name quoted in errors.
        last_dim: required size of the last axis, or None for any shape.
    """
    if not is_torch(values):
        values = np.asarray(values)
        if not np.issubdtype(values.dtype, np.floating):
            values = values.astype(np.float64)
    elif not values.is_floating_point():
        values = values.double()
    if last_dim is not None and (values.ndim == 0 or values.shape[-1] != last_dim):
        raise ValueError(f"{name} must have shape (..., {last_dim}), got {tuple(values.shape)}")
    return values


@dataclass(frozen=True, eq=False)
class Lane:
    """One lane: a centreline polyline with a constant width.

    Consecutive duplicate points of ``centerline`` are dropped (the geometry is
    unchanged); at least two distinct points must remain. Equality is identity.

    Attributes:
        centerline: (N, 2) [m] points in driving order, world frame.
        width: lane width [m], > 0.
        lane_id: unique id within a map, e.g. ``"a->b#0"`` for highway-env lanes.
        speed_limit: [m/s], > 0, or None when the source has none.
        successors: ids of the lanes that continue this one.
    """

    centerline: np.ndarray
    width: float
    lane_id: str
    speed_limit: float | None = None
    successors: tuple[str, ...] = ()
    _arclength: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        points = np.array(self.centerline, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 2:
            raise ValueError(
                f"Lane.centerline must have shape (N, 2) [m], got {tuple(points.shape)}"
            )
        if not np.all(np.isfinite(points)):
            raise ValueError("Lane.centerline must be finite")
        keep = np.ones(len(points), dtype=bool)
        keep[1:] = np.any(np.diff(points, axis=0) != 0.0, axis=1)
        points = points[keep]
        if len(points) < 2:
            raise ValueError("Lane.centerline needs at least 2 distinct points")
        width = finite_number("Lane.width", self.width, "m")
        if not isinstance(self.lane_id, str) or not self.lane_id:
            raise ValueError(f"Lane.lane_id must be a non-empty string, got {self.lane_id!r}")
        speed = self.speed_limit
        if speed is not None:
            speed = finite_number("Lane.speed_limit", speed, "m/s")
        successors = tuple(self.successors)
        if not all(isinstance(s, str) for s in successors):
            raise ValueError(f"Lane.successors must be lane id strings, got {successors!r}")
        seg_length = np.linalg.norm(np.diff(points, axis=0), axis=1)
        arclength = np.concatenate([[0.0], np.cumsum(seg_length)])
        for array in (points, arclength):
            array.setflags(write=False)
        object.__setattr__(self, "centerline", points)
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "speed_limit", speed)
        object.__setattr__(self, "successors", successors)
        object.__setattr__(self, "_arclength", arclength)

    @property
    def length(self) -> float:
        """Centreline length [m]."""
        return float(self._arclength[-1])

    @property
    def arclength(self) -> np.ndarray:
        """(N,) [m] arclength of each centreline point, from 0 to ``length``."""
        return self._arclength

    def position(self, s: Array) -> tuple[Array, Array]:
        """Point and heading at arclength ``s``.

        Args:
            s: (...) [m] arclength, clamped to [0, length]; numpy or torch.

        Returns:
            xy: (..., 2) [m] point on the centreline.
            heading: (...) [rad] direction of travel of the segment holding the point
                (piecewise constant along the polyline).
        """
        s = as_query(s, "s")
        xp = namespace(s)
        start, delta, seg_len, seg_s = self._segments(s)
        s = xp.clip(s, 0.0, self.length)
        index = xp.sum(xp.astype(s[..., None] >= seg_s[1:-1], xp.int64), axis=-1)
        fraction = (s - seg_s[index]) / seg_len[index]
        xy = start[index] + fraction[..., None] * delta[index]
        heading = xp.atan2(delta[index][..., 1], delta[index][..., 0])
        return xy, heading

    def project(self, xy: Array) -> tuple[Array, Array]:
        """Nearest point of the centreline to each query point.

        Args:
            xy: (..., 2) [m] query points; numpy or torch (differentiable).

        Returns:
            s: (...) [m] arclength of the nearest centreline point, in [0, length].
            lateral: (...) [m] signed distance to that point, positive to the left of
                the direction of travel. ``|lateral|`` is the Euclidean distance to
                the polyline; for points whose nearest point is interior to a
                segment, ``position(s)[0] + lateral * left_normal == xy``.
        """
        xy = as_query(xy, "xy", last_dim=2)
        xp = namespace(xy)
        start, delta, seg_len, seg_s = self._segments(xy)
        rel = xy[..., None, :] - start  # (..., K, 2)
        t = xp.clip(xp.sum(rel * delta, axis=-1) / seg_len**2, 0.0, 1.0)
        offset = rel - t[..., None] * delta
        dist2 = xp.sum(offset * offset, axis=-1)
        best = xp.argmin(dist2, axis=-1)[..., None]
        t = xp.take_along_axis(t, best, axis=-1)[..., 0]
        off_x = xp.take_along_axis(offset[..., 0], best, axis=-1)[..., 0]
        off_y = xp.take_along_axis(offset[..., 1], best, axis=-1)[..., 0]
        best = best[..., 0]
        s = seg_s[best] + t * seg_len[best]
        cross = delta[best][..., 0] * off_y - delta[best][..., 1] * off_x
        distance = safe_norm(xp, off_x, off_y)
        lateral = xp.where(cross >= 0, distance, -distance)
        return s, lateral

    def _segments(self, like: Array) -> tuple[Array, Array, Array, Array]:
        """(start (K,2), delta (K,2), length (K,), start arclength (K+1,)) in ``like``'s backend."""
        points = constant_like(self.centerline, like)
        arclength = constant_like(self._arclength, like)
        delta = points[1:] - points[:-1]
        return points[:-1], delta, arclength[1:] - arclength[:-1], arclength
