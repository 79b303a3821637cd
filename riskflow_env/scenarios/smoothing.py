"""Kinematic reference filtering of logged tracks (Savitzky-Golay, scipy).

Logged tracks are noisy references: nuScenes tracks are 2 Hz keyframes that ScenarioNet's
converter interpolates linearly to 10 Hz (speed steps every 0.5 s), and detections jitter
by decimetres, so accelerations and jerk taken from the raw logs are mostly artefacts.
:func:`smooth_tracks` fits, over each contiguous run of valid steps of each track, a
cubic polynomial in a sliding window of :data:`WINDOW_STEPS` steps (2.1 s at 10 Hz)
(``scipy.signal.savgol_filter``, ``mode="interp"``: the first and last half-window are
the fit of the edge window) to x and y, and takes the speed from the same fit's first
derivative. The heading is the direction from each fitted position to the next (at a
run's last step the derivative's, turned on by half of the last step's turn):
:func:`riskflow_env.dynamics.rollout` moves a vehicle along its heading at the start of
the step, so with these headings the filtered
track, rolled out from its own actions (:func:`~riskflow_env.dynamics.inverse`),
reproduces itself. The tangent would lag half a step's turn on every step: 0.7 m after
5.2 s on a 33 m circle at 10 m/s. Where the filtered speed is below
:data:`MIN_HEADING_SPEED` the logged heading is kept (a standing car's direction of
motion is noise). A run shorter than the window uses the longest odd window that fits;
a run of at most :data:`POLY_ORDER` + 1 steps is left as logged. Invalid steps are
unchanged.

:func:`riskflow_env.metrics.kinematics.kinematic_p95` reports the 95th percentiles of
|longitudinal acceleration|, |lateral acceleration| and |jerk| (the KDD features), to
compare raw and filtered logs. On the four nuScenes v1.0-mini samples, over the steps of
moving vehicles (> 1 m/s), p95 |a_lon| falls from 6.0-11.0 to 2.1-3.6 m/s^2 and p95
|jerk| from 117-182 to 4.7-8.8 m/s^3 (docs/tutorials/real-data.md); positions move by at most
centimetres at the 95th percentile.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import savgol_filter

from riskflow_env.config import MAX_MAGNITUDE, is_integer, is_number, plain_number
from riskflow_env.dynamics import wrap_angle

WINDOW_STEPS = 21  # [steps] Savitzky-Golay window (2.1 s at 10 Hz: four nuScenes keyframes), odd
POLY_ORDER = 3  # degree of the local polynomial
MIN_HEADING_SPEED = 0.5  # [m/s] below this the logged heading is kept
# Part of the fingerprint of anything cut from smoothed scenes (training-window caches):
# raised whenever the filter's output changes (2: headings along each step's motion).
VERSION = 2


def smooth_tracks(
    states: np.ndarray,
    valid: np.ndarray,
    dt: float = 0.1,
    window: int = WINDOW_STEPS,
    polyorder: int = POLY_ORDER,
) -> np.ndarray:
    """Savitzky-Golay filtered copy of logged tracks (see the module docstring).

    Args:
        states: (N, T, 4) (x [m], y [m], v [m/s], psi [rad]), psi unwrapped along time.
        valid: (N, T) bool.
        dt: time step [s], in (0, ``MAX_MAGNITUDE``]: a number (numpy scalars too), not
            a bool.
        window: window length [steps], odd, > ``polyorder``.
        polyorder: degree of the local polynomial, >= 1.

    Returns:
        (N, T, 4) filtered states; psi stays within pi of the logged heading.
    """
    states = np.asarray(states, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    if states.ndim != 3 or states.shape[-1] != 4 or valid.shape != states.shape[:2]:
        raise ValueError(
            f"states must be (N, T, 4) and valid (N, T), got {states.shape} and {valid.shape}"
        )
    if not (is_integer(polyorder) and polyorder >= 1):
        raise ValueError(f"polyorder must be an int >= 1, got {polyorder!r}")
    if not (is_integer(window) and window % 2 == 1 and window > polyorder):
        raise ValueError(f"window must be an odd int > polyorder = {polyorder}, got {window!r}")
    if not (is_number(dt) and 0 < plain_number(dt) <= MAX_MAGNITUDE):  # bools, NaN are refused
        raise ValueError(f"dt must be a finite number > 0 [s], got {dt!r}")
    dt = float(plain_number(dt))
    out = states.copy()
    for agent, start, stop in _runs(valid):  # load time: a loop over track segments
        length = stop - start
        size = min(window, length - (1 - length % 2))  # longest odd window that fits
        if size <= polyorder:
            continue
        xy = states[agent, start:stop, :2]
        fit = savgol_filter(xy, size, polyorder, axis=0, mode="interp")
        velocity = savgol_filter(xy, size, polyorder, deriv=1, delta=dt, axis=0, mode="interp")
        speed = np.linalg.norm(velocity, axis=1)
        logged = states[agent, start:stop, 3]
        step = np.diff(fit, axis=0)  # the motion over each step but the last
        along = np.arctan2(step[:, 1], step[:, 0])
        tangent = np.arctan2(velocity[-1, 1], velocity[-1, 0])  # the last: half a turn on
        along = np.append(along, tangent + wrap_angle(tangent - along[-1]))
        heading = logged + wrap_angle(along - logged)
        out[agent, start:stop, :2] = fit
        out[agent, start:stop, 2] = speed
        out[agent, start:stop, 3] = np.where(speed >= MIN_HEADING_SPEED, heading, logged)
    return out


def _runs(valid: np.ndarray) -> list[tuple[int, int, int]]:
    """(agent, start, stop) of every maximal run of valid steps."""
    padded = np.pad(valid, ((0, 0), (1, 1))).astype(np.int8)
    change = np.diff(padded, axis=1)
    starts = np.argwhere(change == 1)
    stops = np.argwhere(change == -1)  # row-major order pairs each start with its stop
    return [(int(a), int(s), int(e)) for (a, s), (_, e) in zip(starts, stops, strict=True)]
