"""Per-step event detection: vehicle-vehicle collisions and off-road driving.

Collision = oriented-box overlap (separating axis test over all pairs). Off-road = a
footprint sample (corners, edge midpoints, centre) where the map's signed distance field
is positive, i.e. outside the drivable area.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from riskflow_env._array import Array, namespace
from riskflow_env.dynamics import YAW
from riskflow_env.geometry import footprint_points, pairwise_overlap
from riskflow_env.maps import DrivableMap
from riskflow_env.state import SceneState


@dataclass(frozen=True)
class FrameEvents:
    """What is happening at one step (leading dims ``(A,)`` for one scene, ``(..., A)``
    for a batch of scenes; numpy arrays or torch tensors).

    Attributes:
        collisions: (..., A, A) bool, symmetric, the pair's boxes overlap.
        offroad_fraction: (..., A) share of the 9 footprint samples outside the road.
        sdf_depth: (..., A) largest SDF value over the footprint [m]; > 0 means that far
            outside the drivable area.
        centroid_offroad: (..., A) bool, the centre is off the road (paper-style ORR).
    """

    collisions: Array
    offroad_fraction: Array
    sdf_depth: Array
    centroid_offroad: Array

    @cached_property
    def collided(self) -> Array:
        """(..., A) bool, the agent overlaps at least one other vehicle."""
        return namespace(self.collisions).any(self.collisions, axis=-1)

    @cached_property
    def offroad(self) -> Array:
        """(..., A) bool, at least one footprint sample is off the road."""
        return self.offroad_fraction > 0.0


def contact_pairs(collisions: Array) -> set[tuple[int, int]]:
    """The slot pairs ``(i, j)``, ``i < j``, in contact in one scene's (A, A) ``collisions``.

    A collision *event* is a pair entering this set (absent at the previous step): the
    event log (``collisions`` of its summary, the harness metric) and the renderer's
    on-screen counter both count them so.
    """
    return {(i, j) for i, j in np.argwhere(np.triu(np.asarray(collisions))).tolist()}


def detect(
    state: SceneState, drivable_map: DrivableMap, footprint_sdf: Array | None = None
) -> FrameEvents:
    """Collisions and off-road flags of the present vehicles in ``state``.

    Args:
        state: a :class:`SceneState`, or any object with ``current`` (..., A, 4),
            ``length``, ``width`` (..., A) [m] and ``present`` (..., A) bool arrays (a
            batch of scenes sharing ``drivable_map``), numpy or torch.
        drivable_map: the scenes' map.
        footprint_sdf: (..., A, 9) the map SDF [m] at the footprint points
            (:func:`~riskflow_env.geometry.footprint_points`), when the caller has looked
            it up already (one lookup for all points of a step).
    """
    current = state.current
    xp = namespace(current)
    xy, yaw = current[..., :2], current[..., YAW]
    present = state.present
    collisions = pairwise_overlap(xy, yaw, state.length, state.width, valid=present)
    sdf = footprint_sdf
    if sdf is None:
        sdf = drivable_map.sdf_at(footprint_points(xy, yaw, state.length, state.width))
    outside = (sdf > 0.0) & present[..., None]
    return FrameEvents(
        collisions=collisions,
        offroad_fraction=xp.sum(xp.astype(outside, sdf.dtype), axis=-1) / outside.shape[-1],
        sdf_depth=xp.where(present, xp.max(sdf, axis=-1), 0.0),
        centroid_offroad=outside[..., -1],
    )
