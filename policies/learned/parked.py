"""Parked vehicles for training windows: cars beside the road that never move.

Recorded highway-env traffic has hardly any vehicle that stands still for a whole
window, so a generator trained on it has not learned that a parked car stays parked:
on the nuScenes samples the shipped generator kept only 56% of the vehicles that stand
still in the log within 2 m of their spot (docs/REALISM.md). With sampled actions a
standing car also creeps: noise in its acceleration is clipped at zero speed on the
way down and not on the way up. :func:`add_parked` adds such cars to a scene, so that
recovery copies (``RecoveryConfig.parked``) show them.

A parked car is put beside the road next to a point of some vehicle's logged track
(a random agent and step, a random side): the first offset along the normal of that
vehicle's heading, from 1.5 m out in 1 m steps, where the map's signed distance is
between half its width plus 0.3 m and plus 3 m (just off the drivable area), facing
along that vehicle's heading (or against it, one in three) with a jitter of up to
0.1 rad. It is kept only if its box stays 0.5 m clear of every logged box of every
agent (``riskflow_env.geometry.separation``) and its centre clear of the other parked
cars by half the sum of the two diagonals plus 0.5 m.

``on_road=True`` parks the car at the kerb instead, on the drivable area: the first
offset where the signed distance is between minus half its width minus 1.5 m and minus
half its width minus 0.2 m (the whole box on the road, its outer side 0.2-1.5 m from the
edge), with the same clearances. The traffic of the log then passes close to a car that
stands in an unused lane, as in a street lined with parked cars (the nuScenes samples'
remaining collisions are moving vehicles driving into standing ones: docs/REALISM.md).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from riskflow_env.dynamics import YAW
from riskflow_env.geometry import separation
from riskflow_env.scenarios.scenario import Scenario

OFFSETS = np.arange(1.5, 13.0, 1.0)  # [m] tried from the track outwards
CANDIDATES_PER_CAR = 8
CLEARANCE = 0.5  # [m] least gap to every logged box (geometry.separation) and other parked cars


def add_parked(
    scenario: Scenario,
    count: int,
    current_index: int,
    rng: np.random.Generator,
    on_road: bool = False,
) -> Scenario:
    """``scenario`` with up to ``count`` parked cars appended as new rows.

    Args:
        scenario: the scene (its map must have a signed distance field, as every map has).
        count: parked cars wanted; fewer are added where the roadside has no room.
        current_index: the window's current step: base points are drawn from the 3 s
            before and the 5.2 s after it.
        rng: the draws.
        on_road: park at the kerb, on the drivable area (module docstring), instead of
            beside the road.

    Returns:
        The scene with the cars as rows after the existing ones: valid at every step,
        speed 0, one pose throughout; lengths in [4, 5] m, widths in [1.7, 2] m.
    """
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
    normal = side[:, None] * np.stack([-np.sin(base[:, YAW]), np.cos(base[:, YAW])], axis=-1)
    points = base[:, None, :2] + OFFSETS[None, :, None] * normal[:, None, :]  # (C, K, 2)
    sdf = np.asarray(scenario.map.sdf_at(points))
    half = width[:, None] / 2
    if on_road:  # the whole box on the road, its outer side near the edge
        fits = (sdf >= -half - 1.5) & (sdf <= -half - 0.2)
    else:  # just off the drivable area
        fits = (sdf >= half + 0.3) & (sdf <= half + 3.0)
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


__all__ = ["add_parked"]
