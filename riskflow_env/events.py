"""Per-step event detection: vehicle-vehicle collisions and off-road driving.

Collision = oriented-box overlap (separating axis test over all pairs). Off-road = a
footprint sample (corners, edge midpoints, centre) where the map's signed distance field
is positive, i.e. outside the drivable area.
"""

from __future__ import annotations

from dataclasses import dataclass

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

    @property
    def collided(self) -> Array:
        """(..., A) bool, the agent overlaps at least one other vehicle."""
        return namespace(self.collisions).any(self.collisions, axis=-1)

    @property
    def offroad(self) -> Array:
        """(..., A) bool, at least one footprint sample is off the road."""
        return self.offroad_fraction > 0.0


def detect(state: SceneState, drivable_map: DrivableMap) -> FrameEvents:
    """Collisions and off-road flags of the present vehicles in ``state``.

    Args:
        state: a :class:`SceneState`, or any object with ``current`` (..., A, 4),
            ``length``, ``width`` (..., A) [m] and ``present`` (..., A) bool arrays (a
            batch of scenes sharing ``drivable_map``), numpy or torch.
        drivable_map: the scenes' map.
    """
    current = state.current
    xp = namespace(current)
    xy, yaw = current[..., :2], current[..., YAW]
    present = state.present
    collisions = pairwise_overlap(xy, yaw, state.length, state.width, valid=present)
    sdf = drivable_map.sdf_at(footprint_points(xy, yaw, state.length, state.width))  # (..., A, 9)
    outside = (sdf > 0.0) & present[..., None]
    return FrameEvents(
        collisions=collisions,
        offroad_fraction=xp.mean(xp.astype(outside, sdf.dtype), axis=-1),
        sdf_depth=xp.where(present, xp.max(sdf, axis=-1), 0.0),
        centroid_offroad=outside[..., -1],
    )
