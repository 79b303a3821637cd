"""A user's planner file, as the ``riskflow-stress`` tests write it to disk."""

from __future__ import annotations

import textwrap

# ``reckless`` steers into the nearest vehicle: a failure within a few steps on a busy scene.
RECKLESS = textwrap.dedent(
    """
    import numpy as np

    def reckless(observation, view):
        others = observation[6:94].reshape(8, 11)
        present = others[:, 10] > 0
        if not present.any():
            return np.array([2.0, 0.0])
        distance = np.where(present, np.hypot(others[:, 0], others[:, 1]), np.inf)
        dx, dy = others[np.argmin(distance), :2]
        return np.array([3.0, np.clip(2.0 * np.arctan2(dy, dx), -1.0, 1.0)])
    """
)
