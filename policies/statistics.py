"""Confidence intervals and tests of the reports: one home for the statistics.

* :func:`wilson_interval`: a rate (collisions per episode) with its Wilson score interval;
  :func:`rate` the same as a report entry ``{"value", "low", "high", "n"}``;
* :func:`mean_summary`: a mean with its bootstrap interval, as such an entry;
* :func:`per_km`: events per kilometre driven, with the exact Poisson interval;
* :func:`mean_interval`: a mean (time to collision, distance) with a seeded percentile
  bootstrap interval;
* :func:`paired_difference`: two policies on the same episodes: the difference of their
  rates with Agresti and Min's interval for matched pairs and McNemar's exact test
  (``scipy.stats.binomtest`` on the discordant pairs).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy import stats


def wilson_interval(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion; (nan, nan) without trials."""
    if trials == 0:
        return math.nan, math.nan
    interval = stats.binomtest(successes, trials).proportion_ci(confidence, method="wilson")
    return float(interval.low), float(interval.high)


def rate(hits: int, trials: int, confidence: float = 0.95) -> dict[str, Any]:
    """``{"value", "low", "high", "n"}`` of a rate with its Wilson interval (None when
    there is no trial)."""
    if trials == 0:
        return {"value": None, "low": None, "high": None, "n": 0}
    low, high = wilson_interval(hits, trials, confidence)
    return {"value": hits / trials, "low": low, "high": high, "n": trials}


def per_km(events: int, metres: float, confidence: float = 0.95) -> dict[str, Any]:
    """``{"value", "low", "high", "n"}`` of an event rate per kilometre driven (``n``: the
    events), with the exact Poisson interval for a count over an exposure (Garwood 1936:
    ``chi2(a/2; 2k) / 2`` and ``chi2(1 - a/2; 2k + 2) / 2`` events, over the distance). The
    counter-metric of a per-episode rate: an ego that crawls collides in few episodes but
    not in fewer per kilometre. None without distance."""
    if not metres > 0:
        return {"value": None, "low": None, "high": None, "n": events}
    km, alpha = metres / 1000.0, 1.0 - confidence
    low = stats.chi2.ppf(alpha / 2, 2 * events) / 2 if events else 0.0
    high = stats.chi2.ppf(1 - alpha / 2, 2 * events + 2) / 2
    return {"value": events / km, "low": float(low) / km, "high": float(high) / km, "n": events}


def mean_interval(
    values: list[float], confidence: float = 0.95, resamples: int = 2000
) -> tuple[float, float]:
    """Percentile-bootstrap interval of the mean of ``values`` (seeded: deterministic;
    inside the range of the data); (nan, nan) for fewer than two values."""
    values = np.asarray(values, dtype=np.float64)
    if values.size < 2:
        return math.nan, math.nan
    draws = np.random.default_rng(0).integers(values.size, size=(resamples, values.size))
    means = values[draws].mean(axis=1)
    low, high = np.quantile(means, [0.5 - confidence / 2, 0.5 + confidence / 2])
    return float(low), float(high)


def mean_summary(values: list[float | None], confidence: float = 0.95) -> dict[str, Any]:
    """The mean of the finite ``values`` (None and NaN left out) with its bootstrap
    interval, as an entry of :func:`summarize` (None where undefined)."""
    finite = [value for value in values if value is not None and np.isfinite(value)]
    low, high = mean_interval(finite, confidence)
    mean = float(np.mean(finite)) if finite else math.nan
    return _entry(mean, low, high, len(finite))


def _entry(value: float, low: float, high: float, count: int) -> dict[str, Any]:
    """A JSON-ready summary entry: NaN becomes None."""
    clean = [None if math.isnan(x) else x for x in (value, low, high)]
    return dict(zip(("value", "low", "high"), clean, strict=True)) | {"n": count}


def paired_difference(counts: dict[str, int], confidence: float = 0.95) -> dict[str, Any]:
    """Trained minus untrained rate on paired episodes, with its interval and test.

    The interval is Agresti and Min's: the Wald interval of a difference of paired
    proportions after adding 1/2 to each cell of the 2x2 table, ``d* +- z sqrt((b + c + 1 -
    (b - c)^2 / n*) / n*^2)`` with ``n* = n + 2``, ``d* = (b - c) / n*`` and ``b``, ``c`` the
    discordant counts, clipped to [-1, 1] (A. Agresti and Y. Min, "Simple improved
    confidence intervals for comparing matched proportions", Statistics in Medicine 24,
    2005). Unlike the plain Wald interval it does not shrink to a point when no pair is
    discordant, and it keeps its coverage at the few discordant pairs of a small run. The
    p-value is the exact two-sided McNemar test (a binomial test of ``b`` out of ``b + c``
    at 1/2; McNemar 1947). Pairing removes the between-scene variance that unpaired
    intervals carry, so it detects a change that two overlapping Wilson intervals cannot.

    Args:
        counts: :func:`paired_counts` (or their sums over runs).
        confidence: level of the interval.

    Returns:
        ``counts`` plus ``difference`` (the observed ``(b - c) / n``), ``low``, ``high``
        and ``p_value``.
    """
    n, b, c = counts["n"], counts["trained_only"], counts["untrained_only"]
    if n == 0:
        return {**counts, "difference": None, "low": None, "high": None, "p_value": None}
    z = stats.norm.ppf(0.5 + confidence / 2)
    total = n + 2  # the table with 1/2 added to each of its four cells
    centre = (b - c) / total
    half = z * np.sqrt(b + c + 1 - (b - c) ** 2 / total) / total
    p_value = stats.binomtest(b, b + c, 0.5).pvalue if b + c else 1.0
    return {
        **counts,
        "difference": (b - c) / n,
        "low": max(centre - half, -1.0),
        "high": min(centre + half, 1.0),
        "p_value": float(p_value),
    }
