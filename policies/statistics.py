"""Confidence intervals and tests of the reports: one home for the statistics.

* :func:`wilson_interval`: a rate (collisions per episode) with its Wilson score interval;
  :func:`rate` the same as a report entry ``{"value", "low", "high", "n"}``;
* :func:`mean_summary`: a mean with its bootstrap interval, as such an entry;
* :func:`mean_interval`: a mean (time to collision, distance) with a seeded percentile
  bootstrap interval;
* :func:`paired_difference`: two policies on the same episodes: the difference of their
  rates with a Wald interval on the discordant pairs and McNemar's exact test
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
