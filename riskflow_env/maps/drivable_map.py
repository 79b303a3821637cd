"""DrivableMap: a boolean drivable-area raster, its signed distance field, and lanes.

Conventions (docs/explanation/architecture.md):

* World frame in metres; ``origin`` is the world (x, y) of the lower-left corner of
  pixel [0, 0]; row ``i`` covers y in [oy + i*res, oy + (i+1)*res), column ``j``
  covers x in [ox + j*res, ox + (j+1)*res). Rows follow +y, columns follow +x.
* ``sdf`` [m] is negative inside the drivable area, positive outside, zero on the
  boundary. Beyond the raster its border pixels continue outward (the lookups clamp
  onto them): a road that crosses the border goes on straight, with the border pixel's
  SDF, so vehicles can drive off the map where its roads leave it; off-road ground stays
  off-road, its SDF growing with the distance out of the raster
  (:func:`~riskflow_env.maps.sampling.bilinear`). The builders run the roads that leave
  the map to the border (:func:`~riskflow_env.maps.builders.from_lanes`).
* Lookups (``sdf_at``, ``is_drivable``, ``crop``) take numpy arrays or torch tensors
  (any device, differentiable wrt the query) through one implementation; the torch
  copy of each raster is made once per (device, dtype) and kept on the map.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from riskflow_env._array import Array, is_torch, namespace
from riskflow_env.kernel_loading import optional_kernels
from riskflow_env.maps._validate import finite_number, number_in_range
from riskflow_env.maps.lanes import Lane, as_query
from riskflow_env.maps.rasterize import signed_distance
from riskflow_env.maps.sampling import (
    bilinear,
    bilinear_with_gradient,
    constant_like,
    crop_offsets,
    crop_points,
)

CropLayer = Literal["drivable", "sdf"]
RESOLUTION_RANGE = (0.01, 10.0)  # [m/px] pixel sizes a map may have
MAX_MAP_COORDINATE = 1e7  # [m] largest |x|, |y| of the raster's corners and of lane points
MAX_LANE_WIDTH = 50.0  # [m] widest lane
MAX_SPEED_LIMIT = 100.0  # [m/s] highest lane speed limit


@dataclass(frozen=True, eq=False)
class DrivableMap:
    """Drivable-area raster with a signed distance field and optional lane centrelines.

    Inputs are copied and made read-only. Equality is identity.

    Attributes:
        drivable: (H, W) bool, True where driving is allowed; H, W >= 2 and at least
            one True pixel.
        resolution: pixel size [m/px], in ``RESOLUTION_RANGE`` (0.01 to 10).
        origin: (2,) [m] world (x, y) of the lower-left corner of pixel [0, 0]; the
            raster's corners lie within +-``MAX_MAP_COORDINATE`` (1e7 m).
        sdf: (H, W) float32 [m] signed distance to the drivable boundary, negative
            inside; computed from ``drivable`` when None. A given one must agree in
            sign (``sdf <= 0`` exactly where ``drivable``) and stay within the
            raster's size, ``(H + W) * resolution``.
        lanes: lane centrelines of the map, unique ids; points within
            +-``MAX_MAP_COORDINATE``, widths at most ``MAX_LANE_WIDTH`` (50 m), speed
            limits at most ``MAX_SPEED_LIMIT`` (100 m/s).
        name: free-form label, e.g. the highway-env family.
    """

    drivable: np.ndarray
    resolution: float
    origin: np.ndarray
    sdf: np.ndarray | None = None
    lanes: tuple[Lane, ...] = ()
    name: str = ""
    _lane_index: dict[str, int] = field(init=False, repr=False)
    _tables: dict[Any, Any] = field(init=False, repr=False, default_factory=dict)

    def __post_init__(self) -> None:
        drivable = np.array(self.drivable)
        if drivable.ndim != 2 or drivable.dtype != np.bool_:
            raise ValueError(
                "DrivableMap.drivable must be a 2-D bool array (H, W), "
                f"got shape {drivable.shape} dtype {drivable.dtype}"
            )
        if min(drivable.shape) < 2:
            raise ValueError(f"DrivableMap.drivable needs H, W >= 2, got {drivable.shape}")
        if not drivable.any():
            raise ValueError("DrivableMap.drivable has no drivable (True) pixel")
        resolution = number_in_range(
            "DrivableMap.resolution", self.resolution, *RESOLUTION_RANGE, "m/px"
        )
        origin = np.array(self.origin, dtype=np.float64)
        if origin.shape != (2,) or not np.all(np.isfinite(origin)):
            raise ValueError(f"DrivableMap.origin must be finite (2,) [m], got {self.origin!r}")
        corner = origin + np.array(drivable.shape[::-1]) * resolution
        if np.max(np.abs([origin, corner])) > MAX_MAP_COORDINATE:
            raise ValueError(
                f"DrivableMap: the raster spans {origin.tolist()} .. {corner.tolist()} m, beyond "
                f"MAX_MAP_COORDINATE = +-{MAX_MAP_COORDINATE:g} m (origin, shape or resolution)"
            )
        if self.sdf is None:
            sdf = signed_distance(drivable, resolution)
        else:
            sdf = np.array(self.sdf, dtype=np.float32)
            if sdf.shape != drivable.shape:
                raise ValueError(
                    f"DrivableMap.sdf must have drivable's shape {drivable.shape}, got {sdf.shape}"
                )
            reach = (sum(drivable.shape) + 1) * resolution
            if not (np.all(np.isfinite(sdf)) and -reach <= sdf.min() and sdf.max() <= reach):
                raise ValueError(f"DrivableMap.sdf must be finite and within +-{reach:g} m")
            if np.any((sdf <= 0) != drivable):
                raise ValueError("DrivableMap.sdf must be <= 0 exactly where drivable is True")
        lanes = tuple(self.lanes)
        if not all(isinstance(lane, Lane) for lane in lanes):
            raise ValueError("DrivableMap.lanes must hold Lane objects")
        _check_lane_ranges(lanes)
        index = {lane.lane_id: i for i, lane in enumerate(lanes)}
        if len(index) != len(lanes):
            raise ValueError("DrivableMap.lanes must have unique lane_id values")
        if not isinstance(self.name, str):
            raise ValueError(f"DrivableMap.name must be a string, got {self.name!r}")
        for array in (drivable, origin, sdf):
            array.setflags(write=False)
        for name, value in (
            ("drivable", drivable),
            ("resolution", resolution),
            ("origin", origin),
            ("sdf", sdf),
            ("lanes", lanes),
            ("_lane_index", index),
        ):
            object.__setattr__(self, name, value)

    def __repr__(self) -> str:
        return (
            f"DrivableMap(name={self.name!r}, shape={self.shape}, resolution={self.resolution}, "
            f"bounds={tuple(round(b, 3) for b in self.bounds)}, lanes={len(self.lanes)})"
        )

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_tables"] = {}  # device copies are rebuilt on demand
        return state

    @property
    def shape(self) -> tuple[int, int]:
        """Raster shape (H, W) [px]."""
        return self.drivable.shape

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) [m] covered by the raster."""
        height, width = self.shape
        ox, oy = (float(v) for v in self.origin)
        return ox, oy, ox + width * self.resolution, oy + height * self.resolution

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """Same as :attr:`bounds`: (xmin, ymin, xmax, ymax) [m]."""
        return self.bounds

    def sdf_at(self, xy: Array) -> Array:
        """Signed distance [m] at world points, bilinear over pixel centres.

        Beyond the outermost pixel centres the border continues outward: the value is
        the nearest border pixel's on a road that crosses the border, and off the road
        that value plus the distance to it (:func:`~riskflow_env.maps.sampling.bilinear`).

        Args:
            xy: (..., 2) [m], numpy or torch (differentiable wrt ``xy``).

        Returns:
            (...) [m], negative on the road.
        """
        xy = as_query(xy, "xy", last_dim=2)
        return bilinear(self._table("sdf", xy), xy, self._origin, self.resolution, extend=True)

    def sdf_with_gradient(self, xy: Array) -> tuple[Array, Array]:
        """:meth:`sdf_at` and its gradient with respect to ``xy``, without autograd.

        Args:
            xy: (..., 2) [m], numpy or torch.

        Returns:
            (...) [m] signed distances and (..., 2) their gradient [m/m]
            (:func:`~riskflow_env.maps.sampling.bilinear_with_gradient`).
        """
        xy = as_query(xy, "xy", last_dim=2)
        table = self._table("sdf", xy)
        return bilinear_with_gradient(table, xy, self._origin, self.resolution, extend=True)

    def is_drivable(self, xy: Array) -> Array:
        """(...) bool: ``sdf_at(xy) <= 0`` for world points ``xy`` (..., 2) [m]."""
        return self.sdf_at(xy) <= 0

    def crop(
        self,
        xy: Array,
        yaw: Array,
        size: int = 64,
        resolution: float | None = None,
        layer: CropLayer = "drivable",
    ) -> Array:
        """Agent-centred, heading-aligned crops, sampled bilinearly.

        The agent sits at the crop centre; columns increase along its heading and
        rows increase to its left (see :func:`~riskflow_env.maps.sampling.crop_points`).

        Args:
            xy: (N, 2) [m] agent positions, numpy or torch.
            yaw: (N,) [rad] agent headings, same backend as ``xy``.
            size: crop side [px], >= 1.
            resolution: crop pixel size [m/px]; the map's when None.
            layer: "drivable" gives the drivable fraction in [0, 1], beyond the raster
                its border pixel's; "sdf" gives the signed distance [m] (:meth:`sdf_at`).

        Returns:
            (N, size, size) in ``xy``'s backend, dtype and device.
        """
        xy = as_query(xy, "xy", last_dim=2)
        yaw = as_query(yaw, "yaw")
        if xy.ndim != 2 or yaw.shape != xy.shape[:1]:
            raise ValueError(
                f"crop needs xy (N, 2) and yaw (N,), got {tuple(xy.shape)} and {tuple(yaw.shape)}"
            )
        if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
            raise ValueError(f"crop size must be an int >= 1 [px], got {size!r}")
        if resolution is not None:
            resolution = finite_number("crop resolution", resolution, "m/px")
        if layer not in ("drivable", "sdf"):
            raise ValueError(f"crop layer must be 'drivable' or 'sdf', got {layer!r}")
        kernels = optional_kernels("riskflow_env.maps.crop_kernels", "the compiled map crops")
        if kernels is not None and _float32_numpy(xy, yaw):  # numpy's values, bit for bit
            return self._compiled_crop(kernels, xy, yaw, int(size), resolution, layer)
        points = crop_points(xy, yaw, int(size), resolution or self.resolution)
        if layer == "sdf":
            return bilinear(self._table("sdf", xy), points, self._origin, self.resolution, True)
        if layer == "drivable":
            ox, oy = self._origin
            padded_origin = (ox - self.resolution, oy - self.resolution)
            table = self._table("drivable_padded", xy)
            return bilinear(table, points, padded_origin, self.resolution, extend=False)
        raise AssertionError(layer)

    def _compiled_crop(self, kernels, xy, yaw, size, resolution, layer) -> np.ndarray:
        """:meth:`crop` of float32 numpy queries by :mod:`~riskflow_env.maps.crop_kernels`."""
        ox, oy = self._origin
        if layer == "drivable":  # the padded raster starts one pixel earlier
            ox, oy = ox - self.resolution, oy - self.resolution
        offsets = crop_offsets(size, resolution or self.resolution).astype(np.float32)
        out = np.empty((len(xy), size, size), dtype=np.float32)
        kernels.crop(
            self._table("sdf" if layer == "sdf" else "drivable_padded", xy), ox, oy,
            self.resolution, layer == "sdf", np.ascontiguousarray(xy), np.cos(yaw),
            np.sin(yaw), offsets, out,
        )  # fmt: skip
        return out

    def lane_by_id(self, lane_id: str) -> Lane:
        """The lane with id ``lane_id``; KeyError naming the known ids otherwise."""
        try:
            return self.lanes[self._lane_index[lane_id]]
        except KeyError:
            known = ", ".join(sorted(self._lane_index)) or "none"
            raise KeyError(f"unknown lane_id {lane_id!r}; map {self.name!r} has: {known}") from None

    def nearest_lane(self, xy: Array) -> tuple[Array, Array, Array]:
        """Closest lane centreline to each point (Euclidean distance to the polyline).

        Args:
            xy: (..., 2) [m], numpy or torch.

        Returns:
            index: (...) int64 index into ``lanes``.
            s: (...) [m] arclength of the nearest point on that lane.
            lateral: (...) [m] signed offset from it, positive to the left.
        """
        if not self.lanes:
            raise ValueError(f"map {self.name!r} has no lanes")
        xy = as_query(xy, "xy", last_dim=2)
        xp = namespace(xy)
        projections = [lane.project(xy) for lane in self.lanes]
        s_all = xp.stack([s for s, _ in projections], axis=-1)
        lateral_all = xp.stack([lat for _, lat in projections], axis=-1)
        best = xp.argmin(xp.abs(lateral_all), axis=-1)[..., None]
        s = xp.take_along_axis(s_all, best, axis=-1)[..., 0]
        lateral = xp.take_along_axis(lateral_all, best, axis=-1)[..., 0]
        return best[..., 0], s, lateral

    @property
    def _origin(self) -> tuple[float, float]:
        return float(self.origin[0]), float(self.origin[1])

    def _table(self, name: str, like: Array) -> Array:
        """Raster ``name`` in ``like``'s backend (torch copies cached per device/dtype)."""
        if name not in self._tables:
            if name == "sdf":
                self._tables[name] = self.sdf
            else:  # drivable as float with a one-pixel ring repeating the border pixels
                self._tables[name] = np.pad(self.drivable.astype(np.float32), 1, mode="edge")
        base = self._tables[name]
        if not is_torch(like):
            return base
        key = (name, str(like.device), like.dtype)
        if key not in self._tables:
            self._tables[key] = constant_like(base, like)
        return self._tables[key]


def _float32_numpy(*arrays: Any) -> bool:
    return all(type(a) is np.ndarray and a.dtype == np.float32 for a in arrays)


def _check_lane_ranges(lanes: tuple[Lane, ...]) -> None:
    """ValueError naming the first lane whose points, width or speed limit lie beyond
    ``MAX_MAP_COORDINATE``, ``MAX_LANE_WIDTH`` or ``MAX_SPEED_LIMIT``."""
    for lane in lanes:
        if np.max(np.abs(lane.centerline)) > MAX_MAP_COORDINATE:
            problem = f"a point beyond MAX_MAP_COORDINATE = +-{MAX_MAP_COORDINATE:g} m"
        elif lane.width > MAX_LANE_WIDTH:
            problem = f"width {lane.width:g} m > MAX_LANE_WIDTH = {MAX_LANE_WIDTH:g} m"
        elif lane.speed_limit is not None and lane.speed_limit > MAX_SPEED_LIMIT:
            problem = (
                f"speed limit {lane.speed_limit:g} m/s > MAX_SPEED_LIMIT = {MAX_SPEED_LIMIT:g}"
            )
        else:
            continue
        raise ValueError(f"DrivableMap.lanes: lane {lane.lane_id[:100]!r} has {problem}")
