"""``MapStack``: the signed distance fields of several maps, looked up in one call.

Planning B scenes at once (``policies.pipeline.stages.plan_scenes``) evaluates the
map term of every scene's controllable vehicles in one batched lookup, although each
scene has its own :class:`~riskflow_env.maps.DrivableMap` (own raster size, origin and
resolution). The stack keeps the maps' SDF rasters end to end in one flat table, with
each map's size, origin, resolution and offset; a query point carries the index of its
map. Values and gradients are those of ``DrivableMap.sdf_at`` / ``sdf_with_gradient``
of that map (the same interpolation code, :func:`~riskflow_env.maps.sampling.interpolate_flat`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import array_api_compat
import numpy as np

from riskflow_env._array import Array, asarray_like, is_torch, namespace
from riskflow_env.maps.drivable_map import DrivableMap
from riskflow_env.maps.lanes import as_query
from riskflow_env.maps.sampling import interpolate_flat


class MapStack:
    """Several maps' SDFs in one table (module docstring).

    Args:
        maps: the maps, one or more; map ``m`` is looked up with index ``m``.
    """

    def __init__(self, maps: Sequence[DrivableMap]) -> None:
        maps = tuple(maps)
        if not maps or not all(isinstance(m, DrivableMap) for m in maps):
            raise ValueError("MapStack: maps must be a non-empty sequence of DrivableMap")
        self.maps = maps
        sizes = np.array([m.sdf.size for m in maps], dtype=np.int64)
        self._flat = np.concatenate([m.sdf.reshape(-1) for m in maps])
        self._grid = {
            "height": np.array([m.shape[0] for m in maps], dtype=np.int64),
            "width": np.array([m.shape[1] for m in maps], dtype=np.int64),
            "origin_x": np.array([m.origin[0] for m in maps], dtype=np.float64),
            "origin_y": np.array([m.origin[1] for m in maps], dtype=np.float64),
            "resolution": np.array([m.resolution for m in maps], dtype=np.float64),
            "offset": np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64),
        }
        self._tables: dict[Any, Any] = {}
        self._order: np.ndarray | None = None  # map of each index (a reordered view)
        self.positions = {id(m): i for i, m in enumerate(maps)}  # id(map) -> index

    def view(self, indices: Sequence[int]) -> MapStack:
        """The maps ``indices`` (in that order, repeats allowed) as a stack sharing this
        one's tables (nothing is copied): index ``b`` of the view is map ``indices[b]``."""
        indices = np.asarray(indices, dtype=np.int64)
        if (
            indices.ndim != 1
            or indices.size == 0
            or not np.all((indices >= 0) & (indices < len(self.maps)))
        ):
            raise ValueError(f"indices must be a non-empty list in [0, {len(self.maps)})")
        other = object.__new__(MapStack)
        other.__dict__.update(self.__dict__)
        base = self._order if self._order is not None else np.arange(len(self.maps))
        other._order = base[indices]
        other.maps = tuple(self.maps[i] for i in indices)
        other.positions = {id(m): int(i) for i, m in reversed(list(enumerate(other.maps)))}
        return other

    def __len__(self) -> int:
        return len(self.maps)

    def select(self, index: Array) -> MapStack.Selection:
        """The lookups of the points of map ``index[i]`` in row ``i``.

        Args:
            index: (C,) int map of each row (numpy or torch, as the queries will be).

        Returns:
            an object with ``sdf_at(xy)`` and ``sdf_with_gradient(xy)`` for queries
            ``xy`` (C, ..., 2) [m], as :class:`DrivableMap`'s.
        """
        return MapStack.Selection(self, index)

    def _tables_like(self, like: Array) -> tuple[Array, dict[str, Array]]:
        """The flat SDF table and the per-map geometry in ``like``'s backend (cached)."""
        if not is_torch(like):
            return self._flat, self._grid
        key = (str(like.device), like.dtype)
        if key not in self._tables:
            xp, device = namespace(like), array_api_compat.device(like)
            grid = {  # floats in the queries' dtype, integers as int64
                name: asarray_like(value, like)
                if value.dtype.kind == "f"
                else xp.asarray(value, device=device)
                for name, value in self._grid.items()
            }
            self._tables[key] = (asarray_like(self._flat.copy(), like), grid)
        return self._tables[key]

    class Selection:
        """Lookups with a map per query row (:meth:`MapStack.select`)."""

        def __init__(self, stack: MapStack, index: Array) -> None:
            self.stack, self.index = stack, index
            count = len(stack)
            if len(index) and (int(index.min()) < 0 or int(index.max()) >= count):
                raise ValueError(f"map index must be in [0, {count}), got {index}")
            self._grids: dict[Any, tuple] = {}  # the rows' geometry, per backend and rank

        def _grid(self, xy: Array) -> tuple[Array, tuple]:
            """The flat table and each row's raster geometry, shaped (C, 1, ..., 1) for
            queries like ``xy`` (gathered once per backend, dtype and rank)."""
            key = (is_torch(xy), str(getattr(xy, "device", "")), xy.dtype, xy.ndim)
            if key not in self._grids:
                flat, grid = self.stack._tables_like(xy)
                index, order = self.index, self.stack._order
                if order is not None:
                    index = asarray_like(order, index)[index] if is_torch(index) else order[index]
                lead = (slice(None),) + (None,) * (xy.ndim - 2)  # (C,) -> (C, 1, ..., 1)
                names = ("height", "width", "origin_x", "origin_y", "resolution", "offset")
                self._grids[key] = (flat, tuple(grid[name][index][lead] for name in names))
            return self._grids[key]

        def sdf_at(self, xy: Array) -> Array:
            """(C, ...) [m] signed distances of ``xy`` (C, ..., 2) [m] in each row's map."""
            xy = as_query(xy, "xy", last_dim=2)
            flat, grid = self._grid(xy)
            return interpolate_flat(flat, xy, grid, extend=True, with_gradient=False)[0]

        def sdf_with_gradient(self, xy: Array) -> tuple[Array, Array]:
            """:meth:`sdf_at` and its gradient (C, ..., 2) [m/m] with respect to ``xy``."""
            xy = as_query(xy, "xy", last_dim=2)
            flat, grid = self._grid(xy)
            return interpolate_flat(flat, xy, grid, extend=True, with_gradient=True)


__all__ = ["MapStack"]
