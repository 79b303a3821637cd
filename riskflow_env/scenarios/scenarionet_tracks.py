"""The vehicle tracks of a ScenarioNet description as arrays, on the 10 Hz grid.

What :func:`~riskflow_env.scenarios.scenarionet.load_scenarionet` does to the ``tracks``
of a description before it cuts the scenario window:

* :func:`stack_tracks`: every vehicle's ``position``, ``heading``, ``velocity``,
  ``valid`` and size stacked into (N, T, ...) arrays, each field checked (a step is
  valid only with finite position and heading; N x T and each field's size against
  :mod:`~riskflow_env.scenarios.scenarionet_limits` before it is converted); sizes are
  the median over the valid steps, 0 and NaN counting as not given (:data:`DEFAULT_SIZE`
  when a track gives none; a negative or infinite size is a ValueError), the length the
  larger;
* :func:`time_stamps`: the recorded steps' times (``metadata["ts"]`` or
  ``sample_rate``), finite and increasing;
* :func:`resample`: tracks on the 10 Hz grid (linear in position and velocity,
  shortest-arc in heading; a resampled step is valid when both neighbours are);
* :func:`speed_from_xy`: speeds from position differences when the file has no velocity;
* :func:`hold_nearest_valid`: invalid steps hold the nearest valid state (never NaN).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from riskflow_env.dynamics import wrap_angle
from riskflow_env.scenarios.scenarionet_features import real_array
from riskflow_env.scenarios.scenarionet_limits import MAX_STEPS, check_track_steps
from riskflow_env.untrusted import brief

DT = 0.1  # [s] time step of scenarios
DEFAULT_SIZE = (4.5, 2.0)  # [m] (length, width) of tracks that give none


def stack_tracks(states: list, ids: list[str], source: str) -> tuple:
    """Arrays of all vehicle tracks: xy (N, T, 2), heading (N, T), velocity (N, T, 2) or
    None, valid (N, T) bool, size (N, 2) (length, width) [m]."""
    fields: dict[str, list] = {"position": [], "heading": [], "velocity": [], "valid": []}
    size = np.zeros((len(ids), 2))
    steps = None
    for row, (track_id, state) in enumerate(zip(ids, states, strict=True)):
        if not isinstance(state, Mapping):
            raise ValueError(f"{source}: track {track_id!r} has no 'state' dict")
        for key in ("position", "heading", "valid"):
            if key not in state:
                raise ValueError(f"{source}: track {track_id!r} state has no {key!r}")
        what = f"{source}: track {track_id!r}"
        limit = 3 * (MAX_STEPS if steps is None else steps)  # (T, 3) at most
        position = _read(state["position"], f"{what} position", limit)
        if steps is None:
            steps = len(position) if position.ndim else 0
            check_track_steps(len(ids), steps, source)
        if position.ndim != 2 or position.shape[1] < 2 or len(position) != steps:
            raise ValueError(
                f"{source}: track {track_id!r} position must have shape ({steps}, 2 or 3), "
                f"got {position.shape}"
            )
        valid = _read(state["valid"], f"{what} valid", limit).reshape(-1) != 0
        heading = _read(state["heading"], f"{what} heading", limit).reshape(-1)
        for key, value in (("valid", valid), ("heading", heading)):
            if value.shape != (steps,):
                raise ValueError(f"{source}: track {track_id!r} {key} must have shape ({steps},)")
        valid &= np.all(np.isfinite(position[:, :2]), axis=1) & np.isfinite(heading)
        fields["position"].append(position[:, :2])
        fields["heading"].append(heading)
        fields["valid"].append(valid)
        velocity = state.get("velocity")
        velocity = None if velocity is None else _read(velocity, f"{what} velocity", limit)
        fields["velocity"].append(
            velocity if velocity is not None and velocity.shape == (steps, 2) else None
        )
        for column, key in enumerate(("length", "width")):
            values = _read(state.get(key, ()), f"{what} {key}", limit).reshape(-1)
            values = values[valid] if values.shape == (steps,) else values
            size[row, column] = _median_size(values, f"{what} {key}", DEFAULT_SIZE[column])
    size = np.where(size[:, :1] < size[:, 1:], size[:, ::-1], size)  # length is the larger
    velocities = fields["velocity"]
    velocity = None if any(v is None for v in velocities) else np.stack(velocities)
    if velocity is not None:
        velocity = np.where(np.isfinite(velocity), velocity, 0.0)
    xy = np.stack(fields["position"])
    return xy, np.stack(fields["heading"]), velocity, np.stack(fields["valid"]), size


def _median_size(values: np.ndarray, what: str, default: float) -> float:
    """The median of a track's sizes ``values`` [m] at its valid steps; 0 and NaN mean not
    given and are left out (``default`` when none is given). A negative or infinite size
    is not a missing one: ValueError naming ``what`` (the file, track and field)."""
    given = values[~np.isnan(values) & (values != 0)]
    bad = given[~np.isfinite(given) | (given < 0)]
    if bad.size:
        raise ValueError(
            f"{what} must be > 0 m (0 or NaN: not given) at the valid steps, got {bad[0]:g}"
        )
    return float(np.median(given)) if given.size else default


def _read(value: object, what: str, limit: int) -> np.ndarray:
    return real_array(value, what, limit, "MAX_STEPS")


def time_stamps(metadata: Mapping, steps: int, source: str) -> np.ndarray:
    """(T,) [s] time stamps of the recorded steps."""
    ts = metadata.get("ts")
    if isinstance(ts, np.ndarray):
        size = ts.size
    else:
        size = len(ts) if isinstance(ts, (list, tuple)) else 1
    if ts is not None and size == steps:
        times = _read(ts, f"{source}: metadata['ts']", MAX_STEPS).reshape(-1)
    else:
        rate = metadata.get("sample_rate", DT)
        if not isinstance(rate, (int, float, np.integer, np.floating)):
            raise ValueError(
                f"{source}: metadata['sample_rate'] must be a number, got {brief(rate)}"
            )
        rate = float(rate)
        if not (np.isfinite(rate) and rate > 0):
            raise ValueError(f"{source}: metadata['sample_rate'] must be positive, got {rate}")
        times = np.arange(steps) * rate
    if steps < 1 or not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
        raise ValueError(f"{source}: time stamps must be finite and increasing")
    return times


def resample(
    times: np.ndarray,
    grid: np.ndarray,
    xy: np.ndarray,
    heading: np.ndarray,
    velocity: np.ndarray | None,
    valid: np.ndarray,
) -> tuple:
    """Tracks on the time ``grid`` (G,): linear, heading along the shortest arc."""
    left = np.clip(np.searchsorted(times, grid, side="right") - 1, 0, max(len(times) - 2, 0))
    right = np.minimum(left + 1, len(times) - 1)
    span = np.where(right > left, times[right] - times[left], 1.0)
    frac = np.clip((grid - times[left]) / span, 0.0, 1.0)  # (G,)
    new_valid = (valid[:, left] & valid[:, right]) | (valid[:, left] & (frac == 0.0))
    new_valid |= valid[:, right] & (frac == 1.0)

    def lerp(values: np.ndarray) -> np.ndarray:
        weight = frac.reshape((1, -1) + (1,) * (values.ndim - 2))
        return values[:, left] + weight * (values[:, right] - values[:, left])

    turn = wrap_angle(heading[:, right] - heading[:, left])
    new_heading = heading[:, left] + frac * turn
    new_velocity = None if velocity is None else lerp(velocity)
    return lerp(xy), new_heading, new_velocity, new_valid


def speed_from_xy(xy: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(N, T) [m/s] mean of the backward and forward position differences that exist."""
    step = np.linalg.norm(np.diff(xy, axis=1), axis=-1) / DT  # (N, T-1)
    ok = valid[:, 1:] & valid[:, :-1]
    total = np.zeros(valid.shape)
    count = np.zeros(valid.shape)
    for sl in (np.s_[:, 1:], np.s_[:, :-1]):  # backward, forward
        total[sl] += np.where(ok, step, 0.0)
        count[sl] += ok
    return np.where(count > 0, total / np.maximum(count, 1), 0.0)


def hold_nearest_valid(states: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``states`` (N, T, 4) with invalid steps replaced by the nearest earlier valid state
    (the first valid one before any)."""
    steps = np.arange(valid.shape[1])
    last = np.maximum.accumulate(np.where(valid, steps, -1), axis=1)
    first = np.argmax(valid, axis=1)[:, None]
    source = np.where(last >= 0, last, first)
    return np.take_along_axis(states, source[..., None], axis=1)


__all__ = [
    "DEFAULT_SIZE",
    "DT",
    "hold_nearest_valid",
    "resample",
    "speed_from_xy",
    "stack_tracks",
    "time_stamps",
]
