"""Redraw the CS-RS and realism plots of the committed result folders from their report.md.

    python docs/results/replot.py docs/results/ksweep docs/results/horizon docs/results/ablation

``riskflow-eval report`` needs the per-rollout KDD samples, which are not committed
(docs/explanation/results.md); the metric tables of ``report.md`` hold every value these plots show
(rounded to 3 decimals). ``speed.png`` and ``report.md`` are left as they are.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

from policies.evaluation.plots import write_metric_plots
from policies.evaluation.report import METRIC_COLUMNS, Table

KEYS = {name: key for key, name in METRIC_COLUMNS}
HEADING = re.compile(r"^## K=(\S+), T=(\S+?)(?: s)? \((\d+) scenes")


def tables_from_report(path: Path) -> list[Table]:
    """The metric tables of a ``report.md`` (timings left empty)."""
    tables, lines = [], path.read_text().splitlines()
    for number, line in enumerate(lines):
        match = HEADING.match(line)
        if not match:
            continue
        k, interval, scenes = match.groups()
        metrics = {}
        header = [cell.strip() for cell in lines[number + 2].strip("|").split("|")][2:]
        keys = [KEYS.get(name) for name in header]  # a report's columns, old or new
        for row in lines[number + 4 :]:
            if not row.startswith("|"):
                break
            cells = [cell.strip() for cell in row.strip("|").split("|")]
            values = [float("nan") if c in ("n/a", "ref.") else float(c) for c in cells[2:]]
            found = {key: v for key, v in zip(keys, values, strict=True) if key is not None}
            metrics[cells[0]] = {key: found.get(key, float("nan")) for key in KEYS.values()}
        k_value = None if k == "-" else k if k == "all" else int(k)
        tables.append(Table(k_value, None if interval == "-" else float(interval), int(scenes),
                            metrics, {}))  # fmt: skip
    return tables


def replot(folder: Path) -> list[Path]:
    """Redraw the metric plots of ``folder`` from its ``report.md``; returns the files."""
    return write_metric_plots(tables_from_report(folder / "report.md"), folder)


if __name__ == "__main__":
    for argument in sys.argv[1:]:
        print("\n".join(str(path) for path in replot(Path(argument))))
