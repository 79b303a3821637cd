"""KDD: kinematic distribution distance between generated and logged trajectories.

Three per-step features, from the states' speed and heading (the unicycle model's own
inverse, :func:`riskflow_env.dynamics.inverse`), for the step ``t -> t+1``:

* longitudinal acceleration ``a_t = (v_{t+1} - v_t) / dt`` [m/s^2];
* lateral acceleration (vehicle frame) ``a_lat_t = 0.5 (v_t + v_{t+1}) * omega_t``
  [m/s^2], with the yaw rate ``omega_t = wrap(psi_{t+1} - psi_t) / dt``: the
  centripetal acceleration of a vehicle moving at the step's mean speed along a
  path turning at ``omega``;
* longitudinal jerk ``j_t = (a_{t+1} - a_t) / dt`` [m/s^3].

A sample is kept when every state it uses is valid, its last state is at a scored step
(earlier ones may be context) and its agent is evaluated. Samples are pooled over
agents, steps and rollouts, separately for the simulated tracks and for the logged
reference; KDD per feature is the Wasserstein-1 distance between the two pools
(``scipy.stats.wasserstein_distance``) and ``kdd`` the mean of the three. With every
scene rolled out the same number of times, repeating a scene's reference once per
rollout leaves the reference distribution unchanged.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.stats import wasserstein_distance

from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import ACCEL, SPEED, YAW_RATE, inverse
from riskflow_env.metrics.rollout import RolloutRecord

KINEMATIC_FEATURES = ("longitudinal_acceleration", "lateral_acceleration", "jerk")
_SOURCES = ("generated", "reference")


def kinematic_series(
    states: np.ndarray, valid: np.ndarray, dt: float
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The three KDD features of every agent along time.

    Args:
        states: (A, T, 4) (x [m], y [m], v [m/s], psi [rad]).
        valid: (A, T) bool.
        dt: time step [s].

    Returns:
        name -> (values, ok): for the accelerations (A, T-1), sample ``t`` is the step
        ``t -> t+1``; for the jerk (A, T-2), sample ``t`` spans ``t .. t+2``. ``ok`` is
        True where every state used is valid.
    """
    actions = inverse(states, DynamicsConfig(dt=dt))  # (A, T-1, 2)
    accel = actions[..., ACCEL]
    mean_speed = 0.5 * (states[:, :-1, SPEED] + states[:, 1:, SPEED])
    step_ok = valid[:, :-1] & valid[:, 1:]
    return {
        "longitudinal_acceleration": (accel, step_ok),
        "lateral_acceleration": (mean_speed * actions[..., YAW_RATE], step_ok),
        "jerk": (np.diff(accel, axis=1) / dt, step_ok[:, :-1] & step_ok[:, 1:]),
    }


def kinematic_p95(states: np.ndarray, valid: np.ndarray, dt: float) -> dict[str, float]:
    """95th percentile of |value| of each feature of :func:`kinematic_series` over its
    valid samples (e.g. raw vs filtered logs); NaN for a feature without samples.

    Args:
        states: (A, T, 4) (x [m], y [m], v [m/s], psi [rad]).
        valid: (A, T) bool.
        dt: time step [s].
    """
    result = {}
    for name, (values, ok) in kinematic_series(states, valid, dt).items():
        samples = np.abs(values[ok])
        result[name] = float(np.percentile(samples, 95)) if samples.size else float("nan")
    return result


def kinematic_values(
    states: np.ndarray, valid: np.ndarray, record: RolloutRecord
) -> dict[str, np.ndarray]:
    """Pooled 1-D samples of each feature of ``states`` / ``valid`` (either track of
    ``record``), for the evaluated agents, ending at scored steps."""
    samples = {}
    for name, (values, ok) in kinematic_series(states, valid, record.dt).items():
        span = record.num_steps - values.shape[1]  # states used per sample, minus one
        last = np.arange(values.shape[1]) + span  # index of the last state used
        keep = ok & (last >= record.num_context)[None, :] & record.evaluated[:, None]
        samples[name] = values[keep]
    return samples


def jerk_steps(record: RolloutRecord) -> tuple[np.ndarray, np.ndarray]:
    """Simulated jerk samples (those of :func:`kinematic_values`) with their step index.

    Simulated step ``k`` is the action taken from the reset state (record step
    ``num_context - 1``) on. A jerk sample is the change of acceleration from step
    ``k - 1`` to step ``k`` (for ``k = 0`` the previous acceleration is the logged one).
    With a policy that re-plans every ``period`` steps, ``k mod period == 0`` (``k > 0``)
    are the steps that switch to a new plan, the other ``k`` lie within a plan.

    Returns:
        ``(jerk, step)``: 1-D jerk samples [m/s^3] and their (int) step ``k``.
    """
    values, ok = kinematic_series(record.states, record.valid, record.dt)["jerk"]
    index = np.arange(values.shape[1])  # sample t spans record steps t .. t+2
    keep = ok & (index + 2 >= record.num_context)[None, :] & record.evaluated[:, None]
    step = np.broadcast_to(index + 2 - record.num_context, values.shape)
    return values[keep], step[keep]


@dataclass(frozen=True)
class KinematicSamples:
    """KDD samples of one rollout (or of many, concatenated).

    Attributes:
        generated: feature name -> 1-D samples of the simulated tracks.
        reference: feature name -> 1-D samples of the logged tracks.
    """

    generated: Mapping[str, np.ndarray]
    reference: Mapping[str, np.ndarray]

    def as_arrays(self) -> dict[str, np.ndarray]:
        """Flat ``{"generated_<feature>": ..., "reference_<feature>": ...}`` (for ``np.savez``)."""
        out = {}
        for source in _SOURCES:
            for name, values in getattr(self, source).items():
                out[f"{source}_{name}"] = np.asarray(values)
        return out

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> KinematicSamples:
        """Inverse of :meth:`as_arrays` (e.g. an ``np.load`` result)."""
        return cls(
            *(
                {name: np.asarray(arrays[f"{source}_{name}"]) for name in KINEMATIC_FEATURES}
                for source in _SOURCES
            )
        )

    @classmethod
    def concatenate(cls, samples: Sequence[KinematicSamples]) -> KinematicSamples:
        """All samples of ``samples`` pooled."""

        def pool(source: str) -> dict[str, np.ndarray]:
            return {
                name: np.concatenate([np.zeros(0)] + [getattr(s, source)[name] for s in samples])
                for name in KINEMATIC_FEATURES
            }

        return cls(pool("generated"), pool("reference"))


def kinematic_samples(record: RolloutRecord) -> KinematicSamples:
    """KDD samples of one rollout: its simulated tracks and its reference."""
    return KinematicSamples(
        generated=kinematic_values(record.states, record.valid, record),
        reference=kinematic_values(record.reference, record.reference_valid, record),
    )


def kdd(samples: KinematicSamples | Sequence[KinematicSamples]) -> dict[str, float]:
    """Wasserstein-1 distance per feature over pooled samples, and their mean.

    Args:
        samples: one :class:`KinematicSamples` or a list (pooled first).

    Returns:
        ``{feature: W1}`` for ``KINEMATIC_FEATURES`` (units of the feature: m/s^2,
        m/s^2, m/s^3) and ``"kdd"``, the mean of the three; NaN for a feature without
        samples on either side (and then for ``"kdd"``).
    """
    if not isinstance(samples, KinematicSamples):
        samples = KinematicSamples.concatenate(samples)
    out = {}
    for name in KINEMATIC_FEATURES:
        generated, reference = samples.generated[name], samples.reference[name]
        if generated.size and reference.size:
            out[name] = float(wasserstein_distance(generated, reference))
        else:
            out[name] = float("nan")
    out["kdd"] = float(np.mean([out[name] for name in KINEMATIC_FEATURES]))
    return out


def kdd_over_records(records: Sequence[RolloutRecord]) -> dict[str, float]:
    """:func:`kdd` of the samples of ``records`` pooled."""
    return kdd([kinematic_samples(record) for record in records])
