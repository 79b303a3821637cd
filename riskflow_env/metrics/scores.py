"""CS and RS: the paper's safety-criticality and realism scores across methods.

Both are relative to the methods of one evaluation (one table). With ``norm(m)`` the
min-max normalisation of metric ``m`` across the methods,
``norm(m)_k = (m_k - min_j m_j) / (max_j m_j - min_j m_j)``:

* ``CS_k = norm(SCR)_k``: 1 for the method with the most collisions, 0 for the least;
* ``RS_k = 1 - mean(norm(ORR)_k, norm(ADE)_k, norm(FDE)_k, norm(KDD)_k)``: 1 for a
  method best on every realism metric (lower is better for all four).

Degenerate case: when all methods have the same value of a metric (``max == min``, one
method included), its normalised value is 0 for every method, so the metric neither
lowers RS nor raises CS. A NaN or infinite metric value is left out of the min and max
and gives a NaN normalised value (and score) for its method: an infinite value would make
every other method's normalised value 0 (or NaN). Always report the raw metrics next to
CS and RS: the scores change when a method is added to or removed from the table.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

SAFETY_METRIC = "scr"
REALISM_METRICS = ("orr", "ade", "fde", "kdd")


def min_max_normalise(values: Mapping[str, float]) -> dict[str, float]:
    """Min-max normalisation of ``{method: value}`` to [0, 1].

    Returns:
        ``{method: (v - min) / (max - min)}`` over the finite values; 0 for all when
        ``max == min``; NaN for a NaN or infinite value.
    """
    finite = [v for v in values.values() if math.isfinite(v)]
    if not finite:
        return {method: float("nan") for method in values}
    low, high = min(finite), max(finite)
    span = high - low
    return {
        method: float("nan") if not math.isfinite(v) else (0.0 if span == 0 else (v - low) / span)
        for method, v in values.items()
    }


def safety_realism_scores(
    table: Mapping[str, Mapping[str, float]],
    safety_metric: str = SAFETY_METRIC,
    realism_metrics: Sequence[str] = REALISM_METRICS,
) -> dict[str, dict[str, float]]:
    """CS and RS of every method of one evaluation.

    Args:
        table: ``{method: {metric: value}}``; every method needs ``safety_metric`` and
            every name of ``realism_metrics`` (extra metrics are ignored).
        safety_metric: the metric CS normalises (default ``"scr"``, a rate in [0, 1]).
        realism_metrics: the metrics RS averages, all lower-is-better (default ORR,
            ADE, FDE, KDD).

    Returns:
        ``{method: {"cs": ..., "rs": ...}}``, both in [0, 1] (NaN where an input is NaN or
        infinite).
    """
    if not table:
        return {}
    needed = (safety_metric, *realism_metrics)
    for method, metrics in table.items():
        missing = [name for name in needed if name not in metrics]
        if missing:
            raise ValueError(f"method {method!r} lacks metric(s) {missing} for CS/RS")

    def column(name: str) -> dict[str, float]:
        return min_max_normalise({m: float(metrics[name]) for m, metrics in table.items()})

    cs = column(safety_metric)
    realism = [column(name) for name in realism_metrics]
    return {
        method: {
            "cs": cs[method],
            "rs": 1.0 - sum(norm[method] for norm in realism) / len(realism),
        }
        for method in table
    }
