"""The stress test's headline: failure rates that rank planners, with their intervals.

:func:`stress_summary` aggregates analysed episodes (:class:`Analysed`: a record and its
:class:`~policies.stress.failures.Failure` s). Rates over episodes and over collisions
carry Wilson 95% intervals, means a bootstrap interval (:mod:`policies.statistics`):

=========================  ==============================================================
``ego_collision_rate``     episodes in which the ego collided
``avoidable_failure_rate`` episodes with an ego collision shown avoidable: the headline
                           that ranks planners (a planner is blamed only for what it
                           could have avoided)
``avoidable_share``        ego collisions shown avoidable
``standing_strike_share``  ego collisions with the ego standing (below 0.5 m/s)
``plausible_share``        ego collisions whose attacker stayed within the human bounds
``wreck_share``            ego collisions with a vehicle that had already collided with
                           another (a wreck in the ego's way, or pushed into it)
``attackers_at_impact``    mean guided vehicles within 5 m of the ego at impact
``non_ego_contact_share``  non-ego vehicles in a collision that does not involve the ego
``progress``               mean distance the ego drove [m] (the counter-metric: a
                           planner that stands still is rarely to blame)
``ego_collisions_per_km``  episodes with an ego collision per kilometre the ego drove,
                           with the exact Poisson interval: a planner that crawls
                           collides in few episodes, not in fewer per kilometre
``attacked_rate``          episodes in which a vehicle was guided at some step: with
                           target ``"ego"``, the episodes that put the planner under
                           attack (with ``"others"``, guided toward any vehicle)
``slow_ego_share``         mean share of the ego's steps slower than ``MIN_ATTACK_SPEED``
                           (2 m/s): at a re-plan, the adversary guides no vehicle toward
                           an ego that slow (a standing ego is spared)
=========================  ==============================================================

The last two say how much of the run put the planner under attack: an ego that stands in
a queue for most of an episode is hardly attacked and rarely to blame, and a low
``attacked_rate`` makes a low failure rate weak evidence.

``types`` counts the ego collisions of each :data:`~policies.stress.failures.FAILURE_TYPES`
(with how many were avoidable), ``families`` the ego collision rate per road family.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np

from policies.harness import EGO, EpisodeRecord, mean_summary
from policies.learned.ranking import MIN_ATTACK_SPEED
from policies.statistics import per_km, rate
from policies.stress.failures import FAILURE_TYPES, Failure
from riskflow_env.dynamics import SPEED


@dataclass(frozen=True)
class Analysed:
    """One episode and the analysis of its ego collisions."""

    record: EpisodeRecord
    failures: tuple[Failure, ...]

    def outcome(self) -> dict[str, Any]:
        """The episode as :func:`stress_summary` reads it (JSON-ready, no arrays)."""
        return episode_outcome(self.record, self.failures)


def episode_outcome(record: EpisodeRecord, failures: tuple[Failure, ...]) -> dict[str, Any]:
    """What the summary needs of an episode, JSON-ready (a line of a results file):
    ``scenario``, ``family``, ``steps``, ``failures`` (:meth:`Failure.to_dict` without the
    witness), ``non_ego_contacts`` [in contact, present], ``progress`` [m],
    ``attacked_steps`` (steps in which a vehicle was guided; None for a policy without a
    controllable set) and ``slow_ego_steps`` (steps with the ego slower than
    ``MIN_ATTACK_SPEED``)."""
    rows = []
    for failure in failures:
        row = failure.to_dict()
        row.pop("witness")
        rows.append(row)
    return {
        "scenario": record.scenario.name,
        "family": record.scenario.family or "unknown",
        "steps": int(record.states.shape[1] - 1),
        "failures": rows,
        "non_ego_contacts": list(non_ego_contacts(record)),
        "progress": progress(record),
        "attacked_steps": attacked_steps(record),
        "slow_ego_steps": slow_ego_steps(record),
    }


def attacked_steps(record: EpisodeRecord) -> int | None:
    """Steps in which a vehicle other than the ego was in the controllable set (None: the
    scene policy has none)."""
    if record.guided is None:
        return None
    return int(record.guided[1:, :-1].any(axis=0).sum())


def slow_ego_steps(record: EpisodeRecord) -> int:
    """Steps in which the ego was slower than ``MIN_ATTACK_SPEED`` (its speed when the step's
    action was chosen)."""
    return int((record.states[0, :-1, SPEED] < MIN_ATTACK_SPEED).sum())


def non_ego_contacts(record: EpisodeRecord) -> tuple[int, int]:
    """(non-ego vehicles in a collision without the ego, non-ego vehicles present)."""
    struck = {
        name
        for event in record.events
        if event["event"] == "collision_start" and not event["ego_involved"]
        for name in event["agents"]
    }
    present = [name for name, here in zip(record.agent_names, record.present, strict=True) if here]
    return len(struck), sum(name != EGO for name in present)


def progress(record: EpisodeRecord) -> float:
    """[m] distance the ego drove over the episode."""
    xy = record.states[0, :, :2]
    return float(np.linalg.norm(np.diff(xy, axis=0), axis=-1).sum())


def stress_summary(
    episodes: list[Analysed | dict[str, Any]], confidence: float = 0.95
) -> dict[str, Any]:
    """The summary of module docstring's table, ``types`` and ``families``, from analysed
    episodes or their :func:`episode_outcome` rows."""
    outcomes = [e.outcome() if isinstance(e, Analysed) else e for e in episodes]
    failures = [failure for outcome in outcomes for failure in outcome["failures"]]
    collided = [bool(outcome["failures"]) for outcome in outcomes]
    avoidable = [any(f["avoidable"] for f in outcome["failures"]) for outcome in outcomes]
    contacts = np.array([outcome["non_ego_contacts"] for outcome in outcomes]).reshape(-1, 2)

    def share(flag: str) -> dict[str, Any]:
        return rate(sum(bool(f.get(flag)) for f in failures), len(failures), confidence)

    summary = {
        "episodes": len(outcomes),
        "ego_collisions": len(failures),
        "ego_collision_rate": rate(sum(collided), len(outcomes), confidence),
        "avoidable_failure_rate": rate(sum(avoidable), len(outcomes), confidence),
        "avoidable_share": share("avoidable"),
        "standing_strike_share": share("standing_ego"),
        "plausible_share": share("plausible"),
        "wreck_share": share("wreck"),
        "attackers_at_impact": mean_summary([f["guided_nearby"] for f in failures], confidence),
        "non_ego_contact_share": rate(
            int(contacts[:, 0].sum()), int(contacts[:, 1].sum()), confidence
        ),
        "progress": mean_summary([o["progress"] for o in outcomes], confidence),
        "ego_collisions_per_km": per_km(
            sum(collided), sum(o["progress"] for o in outcomes), confidence
        ),
    }
    # coverage; results files written before these fields existed lack them
    covered = [o for o in outcomes if o.get("attacked_steps") is not None]
    summary["attacked_rate"] = rate(
        sum(o["attacked_steps"] > 0 for o in covered), len(covered), confidence
    )
    timed = [o for o in outcomes if "slow_ego_steps" in o and o["steps"] > 0]
    summary["slow_ego_share"] = mean_summary(
        [o["slow_ego_steps"] / o["steps"] for o in timed], confidence
    )
    kinds = Counter(f["type"] for f in failures)
    saved = Counter(f["type"] for f in failures if f["avoidable"])
    summary["types"] = {
        kind: {"collisions": kinds[kind], "avoidable": saved[kind]} for kind in FAILURE_TYPES
    }
    by_family: dict[str, list[bool]] = {}
    for outcome, hit in zip(outcomes, collided, strict=True):
        by_family.setdefault(outcome["family"], []).append(hit)
    summary["families"] = {
        family: rate(sum(hits), len(hits), confidence) for family, hits in sorted(by_family.items())
    }
    return summary


def counted(count: int, noun: str) -> str:
    """``"1 episode"``, ``"2 episodes"``."""
    return f"{count} {noun}{'' if count == 1 else 's'}"


def headline(summary: dict[str, Any]) -> str:
    """One line: the avoidable-failure rate with its interval, and the counter-metrics."""

    def fmt(entry: dict[str, Any], scale: float = 100.0, unit: str = "%") -> str:
        value, low, high = entry["value"], entry["low"], entry["high"]
        if value is None or math.isnan(value):
            return "n/a"
        interval = "" if low is None else f" [{scale * low:.0f}, {scale * high:.0f}]"
        return f"{scale * value:.0f}{unit}{interval}"

    return (
        f"avoidable failures {fmt(summary['avoidable_failure_rate'])} of "
        f"{counted(summary['episodes'], 'episode')}; ego collisions "
        f"{fmt(summary['ego_collision_rate'])}, "
        f"{fmt(summary['avoidable_share'])} of them avoidable; ego progress "
        f"{fmt(summary['progress'], 1.0, ' m')}"
    )


__all__ = [
    "Analysed",
    "attacked_steps",
    "counted",
    "slow_ego_steps",
    "episode_outcome",
    "headline",
    "non_ego_contacts",
    "progress",
    "rate",
    "stress_summary",
]
