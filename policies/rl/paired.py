"""Trained vs untrained on the same episodes: paired counts, difference, interval and test.

:func:`evaluate` runs every planner on the same (seed, scene) episodes, so a trained ego
and its untrained initial policy can be compared episode by episode. Pairing removes the
between-scene variance that two unpaired intervals carry (some scenes are lost whatever
the ego does), which is what makes a change of a few points measurable on 100-300
episodes.
"""

from __future__ import annotations

from collections.abc import Sequence

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
        :func:`policies.statistics.paired_difference` needs, and what pools across runs by summing.
    """
    if metric not in PAIRED_OUTCOMES:
        raise ValueError(f"metric must be one of {tuple(PAIRED_OUTCOMES)}, got {metric!r}")
    if [r.scenario.name for r in trained] != [r.scenario.name for r in untrained]:
        raise ValueError("trained and untrained must be records of the same episodes, in order")

    def outcome(records: Sequence[EpisodeRecord]) -> np.ndarray:
        keys = PAIRED_OUTCOMES[metric]
        return np.array([any(r.metrics[k] for k in keys) for r in records], dtype=bool)

    return outcome_counts(outcome(trained), outcome(untrained))


def outcome_counts(trained: np.ndarray, untrained: np.ndarray) -> dict[str, int]:
    """:func:`paired_counts` of two (N,) bool arrays of outcomes, episode for episode."""
    a, b = np.asarray(trained, dtype=bool), np.asarray(untrained, dtype=bool)
    return {
        "n": len(a),
        "trained": int(a.sum()),
        "untrained": int(b.sum()),
        "trained_only": int((a & ~b).sum()),
        "untrained_only": int((~a & b).sum()),
    }
