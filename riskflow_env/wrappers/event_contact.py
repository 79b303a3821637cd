"""Where two vehicles touch: the contact point and contact kinds of a collision event.

The contact point is the centroid of the two boxes' overlap (:func:`contact_point`). In a
vehicle's frame it lies towards its front edge ("front"), rear edge ("rear") or a long
side ("side") — whichever the direction to the point exits the box through, i.e.
``|along| / (length / 2)`` against ``|across| / (width / 2)``; an exact corner counts as
"side" (:func:`contact_kind`). The event log
(:class:`~riskflow_env.wrappers.event_log.EventRecorder`) writes both into every
``collision_start``.
"""

from __future__ import annotations

import numpy as np
import shapely

from riskflow_env.geometry import box_corners


def contact_point(
    xy: np.ndarray, yaw: np.ndarray, length: np.ndarray, width: np.ndarray
) -> np.ndarray:
    """Centroid [m] of the overlap of two boxes.

    Args:
        xy: (2, 2) centres [m]; yaw: (2,) [rad]; length, width: (2,) [m].

    Returns:
        (2,) world point; the midpoint of the centres if the boxes only touch.
    """
    corners = box_corners(np.asarray(xy), np.asarray(yaw), np.asarray(length), np.asarray(width))
    overlap = shapely.Polygon(corners[0]).intersection(shapely.Polygon(corners[1]))
    if overlap.is_empty:
        return np.mean(xy, axis=0)
    centroid = overlap.centroid
    return np.array([centroid.x, centroid.y])


def contact_kind(point: np.ndarray, xy: np.ndarray, yaw: float, length: float, width: float) -> str:
    """Where ``point`` (2,) [m] lies for the box (xy (2,) [m], yaw [rad], length, width [m]).

    Returns:
        "front" or "rear" when the direction from the centre to the point leaves the box
        through the front or rear edge, "side" otherwise (corners included).
    """
    dx, dy = np.asarray(point, dtype=np.float64) - xy
    along = dx * np.cos(yaw) + dy * np.sin(yaw)
    across = -dx * np.sin(yaw) + dy * np.cos(yaw)
    if abs(along) * width > abs(across) * length:
        return "front" if along > 0 else "rear"
    return "side"


__all__ = ["contact_kind", "contact_point"]
