"""Shared checks of the map tests."""

from __future__ import annotations

import numpy as np

STEP = 1e-6  # [m], far below a pixel: bilinear is linear within a cell


def numeric_sdf_gradient(drivable_map, points: np.ndarray) -> np.ndarray:
    """(N, 2) central differences of ``drivable_map.sdf_at`` at (N, 2) world ``points``."""
    return np.stack(
        [
            (drivable_map.sdf_at(points + STEP * e) - drivable_map.sdf_at(points - STEP * e))
            / (2 * STEP)
            for e in np.eye(2)
        ],
        axis=-1,
    )
