"""Conflicts between predicted paths, for :class:`~riskflow_env.agents.idm.IDMPolicy`:
box extents in a vehicle's frame, and who yields where two predicted paths meet."""

from __future__ import annotations

import numpy as np

from riskflow_env.geometry import to_frame
from riskflow_env.view import SceneView


def box_extents(relative: np.ndarray, length: np.ndarray, width: np.ndarray) -> tuple:
    """Half extents [m] along and across a frame of boxes (length, width) [m] turned by
    ``relative`` [rad] from it (broadcast): their axis-aligned bounding box there."""
    cos, sin = np.abs(np.cos(relative)), np.abs(np.sin(relative))
    return 0.5 * (cos * length + sin * width), 0.5 * (sin * length + cos * width)


def in_frame(rel: np.ndarray, yaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 2) world offsets -> (dx ahead, dy left) [m] in frames of heading ``yaw`` (...)."""
    return to_frame(rel[..., 0], rel[..., 1], np.cos(yaw), np.sin(yaw))


def yield_gaps(
    view: SceneView,
    rows: np.ndarray,
    path: np.ndarray,
    heading: np.ndarray,
    speed: np.ndarray,
    conflict_margin: float,
    step: float,
) -> np.ndarray:
    """(n,) [m] distance each controlled vehicle may still travel before a predicted
    conflict it must yield in (inf when none).

    A conflict between i and j: at some prediction time their boxes, grown by the
    margins, overlap (j's box bounded by its axis-aligned extent in i's frame). Vehicle
    i yields to j unless j is behind it now; when both would yield to each other and
    both are controlled here, the one farther from the conflict point goes second.
    Vehicles this policy does not control (the ego) are always yielded to.

    Args:
        view: the scene; rows: (n,) the controlled slots.
        path: (A, K, 2) [m] and heading: (A, K) [rad] every vehicle's predicted path at
            prediction times ``step`` [s] apart; speed: (A,) [m/s] its predicted speed.
        conflict_margin: boxes closer than this along (30% of it across) a vehicle are in
            conflict [m].
    """
    count, length, width = view.num_agents, view.length, view.width
    # rows i = the controlled vehicles, columns j = every vehicle: (n, A, K)
    dx, dy = in_frame(path[None] - path[rows, None], heading[rows, None])  # i's frame
    relative = heading[None] - heading[rows, None]
    extent_x, extent_y = box_extents(relative, length[:, None], width[:, None])
    overlap = (np.abs(dx) < 0.5 * length[rows, None, None] + extent_x + conflict_margin) & (
        np.abs(dy) < 0.5 * width[rows, None, None] + extent_y + 0.3 * conflict_margin
    )
    pair = view.present[rows, None] & view.present[None, :] & (rows[:, None] != np.arange(count))
    conflict = overlap.any(axis=-1) & pair
    first = np.argmax(overlap, axis=-1)  # (n, A) first conflicting time index
    behind = dx[..., 0] < -0.5 * length[rows, None]
    must_yield = conflict & ~behind
    point = 0.5 * (
        np.take_along_axis(path[rows, None], first[..., None, None], 2)[:, :, 0]
        + np.take_along_axis(path[None], first[..., None, None], 2)[:, :, 0]
    )
    distance = np.linalg.norm(point - path[rows, None, 0], axis=-1)  # (n, A) i to conflict
    # two controlled vehicles that would yield to each other: the farther one goes second
    mutual, near = must_yield[:, rows], distance[:, rows]  # (n, n)
    farther = (near > near.T) | ((near == near.T) & (rows[:, None] > rows[None, :]))
    must_yield[:, rows] &= ~(mutual & mutual.T) | farther
    travel = speed[rows, None] * step * np.maximum(first - 1, 0)  # last clear distance
    return np.where(must_yield, travel, np.inf).min(axis=-1)
