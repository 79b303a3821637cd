"""Recovery windows: training windows whose agents start off their logged path.

A generator trained only on logged windows never sees itself slightly off course, so in
closed loop, where each plan starts from the small error of the one before, the errors
add up (a generator trained on logs alone left the road in 0.8% of its agent-steps in the
first 2 s of a 10 s closed loop and in 29% in the last 2 s; docs/explanation/realism.md).
ChauffeurNet (Bansal, Krizhevsky & Ogale, "ChauffeurNet: Learning to Drive by Imitating
the Best and Synthesizing the Worst", RSS 2019, section 4.1) synthesises perturbed
trajectories whose history drifts off the log and whose future returns to it; training on
them teaches recovery.

Here a perturbed agent turns away from its log and back: its heading gets a smooth bump
``b(t) = A sin(2 pi tau) + c1 (1 - cos(2 pi tau)) + c2 sin(4 pi tau)``, ``tau = (t - t0)
/ D`` in ``[0, 1]``, over ``D`` seconds that straddle the current step (it lies at ``tau =
phase`` in ``[0.25, 0.75]``: the agent is well out, drifting away or coming back), and
each logged displacement ``p[t+1] - p[t]`` inside the bump is rotated by ``b(t)``; speeds
stay. ``A = pi P / (v_mean D)`` sets the peak lateral drift ``P`` (drawn in ``[-offset,
offset]``; ``|A| <= max_heading``); ``c1, c2`` are fitted (three damped Gauss-Newton
steps) so that the drift left after the bump is small: centimetres on straight roads, at
most about 0.45 m on the curved roads of the training bank (after the bump the track is
the log shifted by that much). Since only headings change, and each step moves along the
new heading by the logged length, a track that follows the unicycle
(``riskflow_env.dynamics``) still follows it exactly, and the window's reference actions
(inverse dynamics of speeds and headings) drive the perturbed reference future; a
recorded real track keeps its own inconsistency, no more. Only agents valid and moving
at ``min_speed`` or more over the whole bump are perturbed (a car standing still cannot
drift sideways), and not those whose bent track would need a yaw rate beyond the
dynamics' bound; the window's map crops and pair features are computed from the
perturbed states by the one window builder (:func:`policies.learned.windows.build_window`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from policies.dataclass_cli import check_at_least, check_field_types
from riskflow_env.dynamics import SPEED, YAW, wrap_angle
from riskflow_env.geometry import from_frame


@dataclass(frozen=True)
class RecoveryConfig:
    """How recovery windows are made (``riskflow-train --recovery-copies``).

    Attributes:
        copies: perturbed copies of each training window (0: none).
        share: probability that an eligible agent of a copy is perturbed.
        offset: largest peak lateral drift [m]; each agent draws one in ``[-offset, offset]``.
        duration: shortest and longest bump ``D`` [s].
        max_heading: cap of the bump amplitudes |A|, |c1|, |c2| [rad].
        min_speed: agents slower than this anywhere in the bump stay on the log [m/s].
        parked: cars parked beside the road added to each copy, clear of the (perturbed)
            tracks (:func:`policies.learned.parked.add_parked`; fewer where there is no room).
        seed: seed of the draws (each window copy has its own stream).
        parked_turn: share of the cars parked beside the road that stand across it, in
            ``[0, 1]`` (``add_parked(turn=...)``).
        parked_jitter: largest noise level [m/s] of the parked cars' logged history,
            ``>= 0`` (``add_parked(jitter=...)``). Both leave the bits and the cache files
            of windows made without them unchanged when 0 (:meth:`settings`).
    """

    copies: int = 0
    share: float = 0.5
    offset: float = 1.0
    duration: tuple[float, float] = (3.0, 6.0)
    max_heading: float = 0.2
    min_speed: float = 2.0
    parked: int = 0
    seed: int = 0
    parked_turn: float = 0.0
    parked_jitter: float = 0.0

    def __post_init__(self) -> None:
        check_field_types(self, "RecoveryConfig")
        check_at_least(self, {"copies": 0, "parked": 0}, owner="RecoveryConfig")
        if not 0.0 <= self.share <= 1.0:
            raise ValueError(f"RecoveryConfig.share must be in [0, 1], got {self.share!r}")
        if not 0.0 <= self.parked_turn <= 1.0:
            raise ValueError(
                f"RecoveryConfig.parked_turn must be in [0, 1], got {self.parked_turn!r}"
            )
        for name in ("offset", "max_heading", "min_speed", "parked_jitter"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"RecoveryConfig.{name} must be a number >= 0, got {value!r}")
        low, high = self.duration
        if not 0 < low <= high or not math.isfinite(high):
            raise ValueError(
                f"RecoveryConfig.duration must be (shortest, longest) with 0 < shortest <= "
                f"longest [s], got {self.duration!r}"
            )

    def settings(self) -> dict:
        """The fields as a dict for cache fingerprints and file names, without
        ``parked_turn`` and ``parked_jitter`` when they are 0 (so caches written before
        they existed stay valid)."""
        settings = dataclasses.asdict(self)
        for name in ("parked_turn", "parked_jitter"):
            if not settings[name]:
                del settings[name]
        return settings


def perturb_tracks(
    tracks: np.ndarray,
    valid: np.ndarray,
    rows: np.ndarray,
    current_index: int,
    dt: float,
    config: RecoveryConfig,
    rng: np.random.Generator,
    yaw_rate_max: float = math.inf,
) -> np.ndarray:
    """A copy of ``tracks`` where some of ``rows`` drift off their log around
    ``current_index`` and come back (module docstring).

    Args:
        tracks: ``(N, T, 4)`` world-frame states (x, y [m], v [m/s], psi [rad]).
        valid: ``(N, T)`` bool.
        rows: the agents that may be perturbed.
        current_index: the window's current step.
        dt: time step [s].
        config: the bump's distribution.
        rng: the draws (amplitude, duration, phase, who).
        yaw_rate_max: the dynamics' yaw-rate bound [rad/s]; an agent whose drift would
            need more (and more than its log) is left on its log.

    Returns:
        ``(N, T, 4)`` float64 tracks; rows not perturbed are the input's.
    """
    rows = np.asarray(rows, dtype=np.int64)
    num_steps = tracks.shape[1]
    count = rows.size
    duration = rng.uniform(*config.duration, count)  # [s]
    phase = rng.uniform(0.25, 0.75, count)
    peak = rng.uniform(-config.offset, config.offset, count)  # [m]
    chosen = rng.random(count) < config.share
    start = current_index - np.round(phase * duration / dt).astype(np.int64)  # (R,)
    tau = (np.arange(num_steps)[None, :] - start[:, None]) * dt / duration[:, None]  # (R, T)
    inside = (tau >= 0.0) & (tau <= 1.0)  # the current step always is
    states = tracks[rows].astype(np.float64)
    speed = np.where(inside, states[..., SPEED], np.nan)
    eligible = (
        chosen
        & (start >= 0)
        & (start + np.ceil(duration / dt) < num_steps)
        & np.all(valid[rows] | ~inside, axis=1)
        & (np.nanmin(speed, axis=1) >= max(config.min_speed, 1e-6))
    )
    mean_speed = np.nanmean(speed, axis=1)
    amplitude = np.clip(
        math.pi * peak / (np.maximum(mean_speed, 1e-6) * duration),
        -config.max_heading,
        config.max_heading,
    )
    phase_angle = 2.0 * math.pi * np.clip(tau, 0.0, 1.0)
    on = eligible[:, None] & inside
    main = np.where(on, np.sin(phase_angle), 0.0)  # (R, T)
    fixes = np.stack(  # (R, T, 2): shapes that cancel the drift left after the bump
        [np.where(on, 1.0 - np.cos(phase_angle), 0.0), np.where(on, np.sin(2 * phase_angle), 0.0)],
        axis=-1,
    )
    steps = np.diff(tracks[rows, :, :2].astype(np.float64), axis=1)  # (R, T - 1, 2)
    steps = np.where((valid[rows, 1:] & valid[rows, :-1])[..., None], steps, 0.0)

    def turned(bend: np.ndarray) -> np.ndarray:
        """The logged steps, each rotated by the heading change at its start."""
        cos, sin = np.cos(bend[:, :-1]), np.sin(bend[:, :-1])
        return np.stack(from_frame(steps[..., 0], steps[..., 1], cos, sin), axis=-1)

    # On a curve, or with a changing speed, the main bump alone leaves up to a metre of
    # drift after it: Gauss-Newton steps on the two correction amounts (damped, as on a
    # straight road only the lateral direction can be corrected, or needs to be).
    extra = np.zeros((count, 2))
    for _ in range(3):
        bend = amplitude[:, None] * main + (fixes * extra[:, None, :]).sum(-1)
        now = turned(bend)
        left = (now - steps).sum(axis=1)  # (R, 2): the drift after the bump
        normal = np.stack([-now[..., 1], now[..., 0]], axis=-1)  # d(step) / d(bend)
        jacobian = np.einsum("rtk,rtc->rkc", normal, fixes[:, :-1])  # (R, 2, 2)
        gram = np.einsum("rkc,rkd->rcd", jacobian, jacobian)
        damping = 1e-2 * np.trace(gram, axis1=1, axis2=2)[:, None, None] + 1e-9
        gradient = np.einsum("rkc,rk->rc", jacobian, left)[..., None]
        extra -= np.linalg.solve(gram + damping * np.eye(2), gradient)[..., 0]
        extra = np.clip(extra, -config.max_heading, config.max_heading)
    bend = amplitude[:, None] * main + (fixes * extra[:, None, :]).sum(-1)
    # An agent whose bent track would need a yaw rate beyond the bound stays on its log.
    logged_rate = wrap_angle(np.diff(tracks[rows, :, YAW].astype(np.float64), axis=1)) / dt
    rate = logged_rate + np.diff(bend, axis=1) / dt
    beyond = (np.abs(rate) > yaw_rate_max + 1e-6) & (np.abs(rate) > np.abs(logged_rate))
    bend = np.where(np.any(beyond & on[:, 1:], axis=1)[:, None], 0.0, bend)
    drift = np.concatenate([np.zeros((count, 1, 2)), np.cumsum(turned(bend) - steps, axis=1)], 1)
    out = tracks.astype(np.float64)
    out[rows, :, :2] += drift
    out[rows, :, YAW] = wrap_angle(out[rows, :, YAW] + bend)
    return out


__all__ = ["RecoveryConfig", "perturb_tracks"]
