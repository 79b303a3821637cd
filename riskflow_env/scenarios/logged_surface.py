"""The ground logged vehicles stand and drive on, as drivable area.

Map data does not always draw every surface a recording's vehicles use: the nuScenes
maps as ScenarioNet converts them carry lanes but no car parks, so a car park's parked
cars stand "off road" at the first step and the off-road detector fires on a logged
replay. The ground under the logged vehicles is drivable by the evidence of the log
itself: :func:`~riskflow_env.scenarios.scenarionet_map.build_map` adds the logged boxes
of every vehicle track (:func:`logged_boxes`) that the lanes and surfaces of the map
data do not cover, each grown by :data:`GROW` (:func:`missing_ground`), and the map is
built again with them. Where the map data has parking areas (``PARKING_LOT``,
``CARPARK_AREA``, ``DRIVEWAY``), those are drawn; where it covers every logged box, the
map is exactly the map data's. What lies
beside the logged vehicles (a car park's empty bays and aisles, the kerb past a parked
car) stays off road.

Boxes: one per valid step of a track, thinned along the track to one every
:data:`SPACING` of travel or :data:`TURN` of heading change (a parked car is one box; a
moving one a box about every metre, and consecutive boxes of a car overlap, so their
union covers the path swept between them). More than :data:`MAX_BOXES` boxes (a long
recording with many tracks) are thinned further by a stride, which keeps the cost
bounded at a coarser coverage.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import shapely

from riskflow_env.dynamics import wrap_angle
from riskflow_env.geometry import box_corners, footprint_points
from riskflow_env.maps import DrivableMap

SPACING = 1.0  # [m] travel between kept boxes of one track
TURN = 0.2  # [rad] heading change between kept boxes of one track
GROW = 0.5  # [m] added around each box: annotation noise and half a raster pixel
MAX_BOXES = 50_000  # boxes tested and drawn at most


class LoggedBoxes(NamedTuple):
    """The logged vehicle boxes that go into the surface (:func:`logged_boxes`)."""

    xy: np.ndarray  # (B, 2) centres [m]
    heading: np.ndarray  # (B,) [rad]
    length: np.ndarray  # (B,) [m]
    width: np.ndarray  # (B,) [m]

    def polygons(self, grow: float = 0.0) -> np.ndarray:
        """(B,) shapely Polygons of the boxes, each side moved out by ``grow`` [m]."""
        return shapely.polygons(
            box_corners(self.xy, self.heading, self.length + 2 * grow, self.width + 2 * grow)
        )


def logged_boxes(
    xy: np.ndarray, heading: np.ndarray, valid: np.ndarray, length: np.ndarray, width: np.ndarray
) -> LoggedBoxes:
    """The boxes of the logged vehicle states, thinned along each track (module docstring).

    Args:
        xy: (N, T, 2) logged box centres [m].
        heading: (N, T) headings [rad].
        valid: (N, T) bool, the log has the state.
        length: (N,) box lengths [m].
        width: (N,) box widths [m].
    """
    rows, steps = box_steps(xy, heading, valid)
    return LoggedBoxes(xy[rows, steps], heading[rows, steps], length[rows], width[rows])


def missing_ground(boxes: LoggedBoxes, drawn: DrivableMap) -> np.ndarray:
    """(M,) shapely Polygons: the ``boxes``, each grown by :data:`GROW`, that stand
    partly off the drivable area of ``drawn`` (the map of the map data alone): a sample
    of the grown footprint (:func:`~riskflow_env.geometry.footprint_points`) where its
    signed distance is positive. Empty when the map data covers them all."""
    grown = footprint_points(boxes.xy, boxes.heading, boxes.length + 2 * GROW,
                             boxes.width + 2 * GROW)  # fmt: skip
    outside = ~np.all(drawn.is_drivable(grown), axis=-1)
    return boxes.polygons(GROW)[outside]


def box_steps(xy: np.ndarray, heading: np.ndarray, valid: np.ndarray) -> tuple:
    """(rows, steps): the indices of the states whose boxes go into the surface, at most
    :data:`MAX_BOXES` (module docstring)."""
    rows, steps = np.nonzero(_kept_steps(xy, heading, valid))
    if rows.size > MAX_BOXES:
        chosen = np.arange(0, rows.size, -(-rows.size // MAX_BOXES))
        rows, steps = rows[chosen], steps[chosen]
    return rows, steps


def _kept_steps(xy: np.ndarray, heading: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(N, T) bool: the steps whose boxes go into the surface. A step is kept when it is
    valid and starts a run of valid steps, ends one, or crosses a multiple of
    :data:`SPACING` of travel or of :data:`TURN` of turning since the track's start."""
    xy, heading = np.where(valid[..., None], xy, 0.0), np.where(valid, heading, 0.0)
    both = valid[:, 1:] & valid[:, :-1]
    travel = np.where(both, np.linalg.norm(np.diff(xy, axis=1), axis=-1), 0.0)
    turn = np.where(both, np.abs(wrap_angle(np.diff(heading, axis=1))), 0.0)
    changed = np.ones(valid.shape, dtype=bool)
    changed[:, 1:] = ~both
    for step, size in ((travel, SPACING), (turn, TURN)):
        bins = np.floor(np.cumsum(step, axis=1) / size)
        changed[:, 1:] |= np.diff(bins, axis=1, prepend=0.0) != 0
    ends = np.ones(valid.shape, dtype=bool)
    ends[:, :-1] = ~both
    return valid & (changed | ends)
