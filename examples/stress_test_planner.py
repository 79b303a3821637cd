"""Stress-test your planner: RiskFlow drives everyone else and looks for its failures.

    python examples/stress_test_planner.py                        # my_planner, 20 scenes
    python examples/stress_test_planner.py --planner idm --scenes 50 --seeds 0 1 2

A planner is a function from the ego's observation (and, if it needs more, the read-only
scene view) to an action (accel [m/s^2], yaw rate [rad/s]); an object may also have
``reset(view)``, called at the start of every episode. Replace :func:`my_planner` with
yours, or give any planner with ``--planner`` (a built-in name, ``package.module:object``
or ``path/to/file.py:object``). This script is the Python call
:func:`policies.stress.riskflow_stress`; the same run from the command line is::

    riskflow-stress --planner examples/stress_test_planner.py:my_planner

Each episode is a scene of the shipped evaluation bank against the adversary with one
noise seed; every ego collision is classified, checked for avoidability (an escape the ego
could have taken, the *witness*) and its attacker held to human bounds. ``--out`` gets
``report.html`` / ``report.md`` (rates with 95% intervals, types, road families, GIFs of
the worst failures), ``summary.json``, ``episodes.jsonl`` and a replay file per failure::

    riskflow-stress replay outputs/stress/failures/<scene>-seed0.npz \\
        --planner examples/stress_test_planner.py:my_planner

docs/tutorials/stress-test.md explains the outputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policies.dataclass_cli import run_main
from policies.stress import riskflow_stress
from policies.stress.cli import stress_kwargs
from policies.stress.runner import StressOptions


def my_planner(observation: np.ndarray, view) -> np.ndarray:
    """Cruise at 12 m/s, brake for a vehicle ahead in a 4 m corridor (2 m plus a 1.5 s gap),
    steer away from the nearer road edge (map SDF 10 m ahead, 30 degrees to each side).
    ``observation`` layout: riskflow_env/observations.py; ``view`` is unused here."""
    speed, length = observation[0], observation[3]
    others = observation[6 : 6 + 8 * 11].reshape(8, 11)  # 8 neighbours in the ego frame
    ahead = (others[:, 10] > 0) & (others[:, 0] > 0) & (np.abs(others[:, 1]) < 2.0)
    gap = np.min(others[ahead, 0] - 0.5 * (length + others[ahead, 8]), initial=np.inf)
    safe = 2.0 + 1.5 * speed  # [m]
    accel = 0.5 * (12.0 - speed) if gap >= safe else -6.0 * (1.0 - max(gap, 0.0) / safe)
    rays = observation[6 + 8 * 11 :].reshape(12, 4)  # direction k at 30 k deg, left positive
    yaw_rate = 0.1 * (rays[11, 2] - rays[1, 2])  # right edge nearer (SDF higher): turn left
    return np.array([np.clip(accel, -8.0, 2.0), np.clip(yaw_rate, -0.5, 0.5)])


@dataclass(frozen=True)
class Options(StressOptions):
    """Options of ``stress_test_planner.py``: those of ``riskflow-stress``."""

    planner: str = "my_planner"
    """my_planner (this file's), a built-in name (idm, sampling_mpc, constant_velocity,
    lane_keeping, replay), package.module:object or path/to/file.py:object"""


def main(options: Options):
    """Run the stress test, print its headline; returns the
    :class:`~policies.stress.StressResult`."""
    planner = my_planner if options.planner == "my_planner" else options.planner
    result = riskflow_stress(planner, options.scenes, options.seeds, **stress_kwargs(options))
    print(result.headline)
    print(f"report: {result.out / 'report.html'}; replay files: {len(result.replays)}")
    return result


if __name__ == "__main__":
    run_main(main, Options, "stress_test_planner.py", __doc__.splitlines()[0])
