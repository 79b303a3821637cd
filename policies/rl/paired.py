"""Trained vs untrained on the same episodes: paired counts, difference, interval and test.

:func:`evaluate` runs every planner on the same (seed, scene) episodes, so a trained ego
and its untrained initial policy can be compared episode by episode. Pairing removes the
between-scene variance that two unpaired intervals carry (some scenes are lost whatever
the ego does), which is what makes a change of a few points measurable on 100-300
episodes.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from policies.harness import EpisodeRecord

PAIRED_OUTCOMES = {
    "ego_collision_rate": ("ego_collided",),
    "ego_failure_rate": ("ego_collided", "ego_offroad"),
}


def paired_counts(
    trained: Sequence[EpisodeRecord], untrained: Sequence[EpisodeRecord], metric: str
) -> dict[str, int]:
    """Outcome counts of two planners on the *same* episodes (scene and adversary seed).

    Args:
        trained, untrained: records of the two planners, episode for episode (as
            :func:`evaluate` returns them for one traffic and the same seeds).
        metric: ``"ego_collision_rate"`` (the episode had an ego collision) or
            ``"ego_failure_rate"`` (a collision or an off-road excursion).

    Returns:
        ``n`` episodes, ``trained`` / ``untrained`` episodes with the outcome, and the
        discordant pairs ``trained_only`` / ``untrained_only``: what
        :func:`paired_difference` needs, and what pools across runs by summing.
    """
    if metric not in PAIRED_OUTCOMES:
        raise ValueError(f"metric must be one of {tuple(PAIRED_OUTCOMES)}, got {metric!r}")
    if [r.scenario.name for r in trained] != [r.scenario.name for r in untrained]:
        raise ValueError("trained and untrained must be records of the same episodes, in order")

    def outcome(records: Sequence[EpisodeRecord]) -> np.ndarray:
        keys = PAIRED_OUTCOMES[metric]
        return np.array([any(r.metrics[k] for k in keys) for r in records], dtype=bool)

    a, b = outcome(trained), outcome(untrained)
    return {
        "n": len(a),
        "trained": int(a.sum()),
        "untrained": int(b.sum()),
        "trained_only": int((a & ~b).sum()),
        "untrained_only": int((~a & b).sum()),
    }


def paired_difference(counts: dict[str, int], confidence: float = 0.95) -> dict[str, Any]:
    """Trained minus untrained rate on paired episodes, with its interval and test.

    The interval is the Wald interval of a difference of paired proportions,
    ``d +- z sqrt((b + c - n d^2) / n^2)`` with ``b``, ``c`` the discordant counts
    (Agresti, *Categorical Data Analysis*, 3rd ed., section 11.1); the p-value is the
    exact two-sided McNemar test (a binomial test of ``b`` out of ``b + c`` at 1/2;
    McNemar 1947). Pairing removes the between-scene variance that unpaired intervals
    carry, so it detects a change that two overlapping Wilson intervals cannot.

    Args:
        counts: :func:`paired_counts` (or their sums over runs).
        confidence: level of the interval.

    Returns:
        ``counts`` plus ``difference``, ``low``, ``high`` and ``p_value``.
    """
    from scipy import stats

    n, b, c = counts["n"], counts["trained_only"], counts["untrained_only"]
    if n == 0:
        return {**counts, "difference": None, "low": None, "high": None, "p_value": None}
    difference = (b - c) / n
    z = stats.norm.ppf(0.5 + confidence / 2)
    half = z * np.sqrt(max(b + c - n * difference**2, 0.0)) / n
    p_value = stats.binomtest(b, b + c, 0.5).pvalue if b + c else 1.0
    return {
        **counts,
        "difference": difference,
        "low": difference - half,
        "high": difference + half,
        "p_value": float(p_value),
    }
