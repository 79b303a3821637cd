"""Per-step event detection: vehicle-vehicle collisions and off-road driving.

Collision = oriented-box overlap (separating axis test over all pairs). Off-road = a
footprint sample (corners, edge midpoints, centre) where the map's signed distance field
is positive, i.e. outside the drivable area.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from riskflow_env.dynamics import YAW
from riskflow_env.geometry import footprint_points, pairwise_overlap
from riskflow_env.maps import DrivableMap
from riskflow_env.state import SceneState


@dataclass(frozen=True)
class FrameEvents:
    """What is happening at one step.

    Attributes:
        collisions: (A, A) bool, symmetric, the pair's boxes overlap.
        offroad_fraction: (A,) share of the 9 footprint samples outside the road.
        sdf_depth: (A,) largest SDF value over the footprint [m]; > 0 means that far
            outside the drivable area.
        centroid_offroad: (A,) bool, the centre is off the road (paper-style ORR).
    """

    collisions: np.ndarray
    offroad_fraction: np.ndarray
    sdf_depth: np.ndarray
    centroid_offroad: np.ndarray

    @property
    def collided(self) -> np.ndarray:
        """(A,) bool, the agent overlaps at least one other vehicle."""
        return self.collisions.any(axis=-1)

    @property
    def offroad(self) -> np.ndarray:
        """(A,) bool, at least one footprint sample is off the road."""
        return self.offroad_fraction > 0.0


def detect(state: SceneState, drivable_map: DrivableMap) -> FrameEvents:
    """Collisions and off-road flags of the present vehicles in ``state``."""
    current = state.current
    xy, yaw = current[:, :2], current[:, YAW]
    collisions = pairwise_overlap(xy, yaw, state.length, state.width, valid=state.present)
    sdf = drivable_map.sdf_at(footprint_points(xy, yaw, state.length, state.width))  # (A, 9)
    present = state.present
    outside = (sdf > 0.0) & present[:, None]
    return FrameEvents(
        collisions=collisions,
        offroad_fraction=outside.mean(axis=-1),
        sdf_depth=np.where(present, sdf.max(axis=-1), 0.0),
        centroid_offroad=outside[:, -1],
    )
