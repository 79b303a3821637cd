"""The comparison table of one (K, planning interval): what the report prints and plots."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Table:
    """The comparison at one (K, planning interval).

    Attributes:
        k: K (None: only methods without K).
        interval: planning interval [s] (None: only methods without one).
        scenes: (scene, seed) pairs every method of the table finished.
        metrics: ``{label: {metric: value}}``, CS and RS included.
        timing: ``{label: {name: value}}`` (seconds, milliseconds as named).
        references: labels of reference methods (outside the CS / RS normalisation).
        safety_metric: the metric CS normalises (``"scr"`` or ``"ego_collision_rate"``).
        left_out: ``{label: rows}`` of the rollouts left out because some other method of
            the table has not run their (scene, seed) (an extension run on fewer scenes,
            an interrupted one); empty when every method ran the same.
    """

    k: int | str | None
    interval: float | None
    scenes: int
    metrics: dict[str, dict[str, float]]
    timing: dict[str, dict[str, float]]
    references: frozenset[str] = frozenset()
    safety_metric: str = "scr"
    left_out: dict[str, int] | None = None

    @property
    def title(self) -> str:
        """``K=5, T=0.5 s``."""
        k = "-" if self.k is None else self.k
        interval = "-" if self.interval is None else f"{self.interval:g} s"
        return f"K={k}, T={interval}"
