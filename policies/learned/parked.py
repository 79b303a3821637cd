"""Parked vehicles for training windows: cars beside the road that never move.

Recorded highway-env traffic has hardly any vehicle that stands still for a whole
window, so a generator trained on it has not learned that a parked car stays parked:
on the nuScenes samples a generator trained without parked cars kept only 56% of the
vehicles that stand still in the log within 2 m of their spot (docs/explanation/realism.md
has what the shipped one keeps). With sampled actions a standing car also creeps: noise
in its acceleration is clipped at zero speed on the way down and not on the way up.
:func:`add_parked` adds such cars to a scene, so that recovery copies
(``RecoveryConfig.parked``) show them.

A parked car is put beside the road next to a point of some vehicle's logged track
(a random agent and step, a random side): the first offset along the normal of that
vehicle's heading, from 1.5 m out in 1 m steps, where the map's signed distance is
between half its width plus 0.3 m and plus 3 m (just off the drivable area), facing
along that vehicle's heading (or against it, one in three) with a jitter of up to
0.1 rad. It is kept only if its box stays 0.5 m clear of every logged box of every
agent (``riskflow_env.geometry.separation``) and its centre clear of the other parked
cars by half the sum of the two diagonals plus 0.5 m.

Two options bring the cars nearer to the parked cars of recorded scenes (in the nuScenes
car park the cars that a generator drives away stand across the lanes, 4-17 m off the
road, and their logged speeds are not 0):

* ``turn``: the share of cars parked across the road (their heading turned by a quarter
  turn, as in the bays of a car park); such a car keeps half its length, not half its
  width, clear of the drivable area.
* ``jitter`` [m/s]: the recorded positions of a parked car wander by centimetres from step
  to step (annotation noise; nuScenes' parked cars show logged speeds of 0.1-0.3 m/s,
  some up to 0.8), and a generator that has only seen exact zeros reads that as a car that
  has started to move. Each car draws a noise level ``sigma`` uniform in ``[0, jitter]``;
  over its history (up to and including the current step) it creeps back and forth along
  its heading with velocity ``sigma * n(t)`` (``n``: unit white noise smoothed over half a
  second, scaled back to unit variance), its speed channel reads ``|sigma * n(t)|``, and
  its position is the integral of that velocity, ending at its spot at the current step.
  Its future stands at the spot with speed 0: the window's reference actions bring a
  jittering car to rest.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.ndimage import uniform_filter1d

from riskflow_env.dynamics import SPEED, YAW
from riskflow_env.geometry import separation
from riskflow_env.scenarios.scenario import Scenario

OFFSETS = np.arange(1.5, 13.0, 1.0)  # [m] tried from the track outwards
CANDIDATES_PER_CAR = 8
CLEARANCE = 0.5  # [m] least gap to every logged box (geometry.separation) and other parked cars
JITTER_SMOOTHING = 0.5  # [s] window of the moving average over the white noise of ``jitter``


def add_parked(
    scenario: Scenario,
    count: int,
    current_index: int,
    rng: np.random.Generator,
    turn: float = 0.0,
    jitter: float = 0.0,
) -> Scenario:
    """``scenario`` with up to ``count`` parked cars appended as new rows.

    Args:
        scenario: the scene (its map must have a signed distance field, as every map has).
        count: parked cars wanted; fewer are added where the roadside has no room.
        current_index: the window's current step: base points are drawn from the 3 s
            before and the 5.2 s after it.
        rng: the draws.
        turn: share of the cars parked across the road, in ``[0, 1]`` (module docstring).
        jitter: largest noise level [m/s] of the cars' logged history, ``>= 0`` (module
            docstring). With ``turn`` and ``jitter`` 0 nothing more is drawn from ``rng``.

    Returns:
        The scene with the cars as rows after the existing ones: valid at every step,
        speed 0, one pose throughout (with ``jitter``, from the current step on);
        lengths in [4, 5] m, widths in [1.7, 2] m.
    """
    if not 0.0 <= turn <= 1.0:
        raise ValueError(f"add_parked: turn must be a share in [0, 1], got {turn!r}")
    if not (np.isfinite(jitter) and jitter >= 0.0):
        raise ValueError(f"add_parked: jitter must be a finite speed >= 0 [m/s], got {jitter!r}")
    if count <= 0:
        return scenario
    states, valid = scenario.states, scenario.valid
    steps = np.arange(max(current_index - 30, 0), min(current_index + 53, states.shape[1]))
    agent, step = np.nonzero(valid[:, steps])
    if agent.size == 0:
        return scenario
    tries = count * CANDIDATES_PER_CAR
    pick = rng.integers(0, agent.size, tries)
    base = states[agent[pick], steps[step[pick]]].astype(np.float64)  # (C, 4)
    side = rng.choice([-1.0, 1.0], tries)
    length, width = rng.uniform(4.0, 5.0, tries), rng.uniform(1.7, 2.0, tries)
    flip = np.where(rng.random(tries) < 1.0 / 3.0, np.pi, 0.0)
    heading = base[:, YAW] + flip + rng.uniform(-0.1, 0.1, tries)
    across = rng.random(tries) < turn if turn else np.zeros(tries, dtype=bool)
    heading = heading + np.where(across, np.pi / 2, 0.0)
    normal = side[:, None] * np.stack([-np.sin(base[:, YAW]), np.cos(base[:, YAW])], axis=-1)
    points = base[:, None, :2] + OFFSETS[None, :, None] * normal[:, None, :]  # (C, K, 2)
    sdf = np.asarray(scenario.map.sdf_at(points))
    half = np.where(across, length, width)[:, None] / 2  # the extent towards the road
    fits = (sdf >= half + 0.3) & (sdf <= half + 3.0)  # just off the drivable area
    found = fits.any(axis=1)
    spot = points[np.arange(tries), fits.argmax(axis=1)]  # (C, 2): first offset that fits
    gap = separation(  # (C, N, T): SAT gap of each candidate to every logged box [m]
        spot[:, None, None, :], heading[:, None, None], length[:, None, None],
        width[:, None, None], states[None, :, :, :2], states[None, :, :, YAW],
        scenario.length[None, :, None], scenario.width[None, :, None],
    )  # fmt: skip
    clear = found & np.all((gap > CLEARANCE) | ~valid[None], axis=(1, 2))
    half_diagonal = 0.5 * np.hypot(length, width)
    kept: list[int] = []
    for candidate in np.flatnonzero(clear):  # greedy over at most count * 8 candidates
        room = [
            np.linalg.norm(spot[candidate] - spot[k])
            > half_diagonal[candidate] + half_diagonal[k] + CLEARANCE
            for k in kept
        ]
        if all(room):
            kept.append(int(candidate))
        if len(kept) == count:
            break
    if not kept:
        return scenario
    chosen = np.array(kept)
    pose = np.concatenate(
        [spot[chosen], np.zeros((chosen.size, 1)), heading[chosen, None]], axis=-1
    )
    parked = np.broadcast_to(pose[:, None, :], (chosen.size, states.shape[1], 4))
    if jitter:
        parked = _jittered(parked, current_index, scenario.dt, jitter, rng)
    extra = {}
    if scenario.agent_ids:
        first = sum(name.startswith("parked-") for name in scenario.agent_ids)
        names = (f"parked-{first + k}" for k in range(chosen.size))
        extra["agent_ids"] = (*scenario.agent_ids, *names)
    if scenario.kinds:
        extra["kinds"] = (*scenario.kinds, *("car",) * chosen.size)
    return dataclasses.replace(
        scenario,
        states=np.concatenate([states, parked.astype(states.dtype)]),
        valid=np.concatenate([valid, np.ones((chosen.size, states.shape[1]), dtype=bool)]),
        length=np.concatenate([scenario.length, length[chosen].astype(scenario.length.dtype)]),
        width=np.concatenate([scenario.width, width[chosen].astype(scenario.width.dtype)]),
        **extra,
    )


def _jittered(
    parked: np.ndarray, current_index: int, dt: float, jitter: float, rng: np.random.Generator
) -> np.ndarray:
    """``parked`` (N, T, 4) with the annotation-like creep of the module docstring over
    the steps up to ``current_index``."""
    count, history = parked.shape[0], current_index + 1
    sigma = jitter * rng.random(count)  # (N,) [m/s]
    width = max(1, round(JITTER_SMOOTHING / dt))
    noise = uniform_filter1d(rng.standard_normal((count, history)), width, axis=1, mode="nearest")
    velocity = sigma[:, None] * noise * np.sqrt(width)  # (N, H) [m/s], signed along the heading
    travelled = np.cumsum(velocity * dt, axis=1)
    along = travelled - travelled[:, -1:]  # (N, H) [m]: 0 at the current step
    out = np.array(parked, dtype=np.float64)
    direction = np.stack([np.cos(out[:, 0, YAW]), np.sin(out[:, 0, YAW])], axis=-1)  # (N, 2)
    out[:, :history, :2] += along[..., None] * direction[:, None, :]
    out[:, :history, SPEED] = np.abs(velocity)
    return out


__all__ = ["add_parked"]
