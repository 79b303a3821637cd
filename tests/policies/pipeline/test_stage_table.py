"""docs/explanation/architecture.md's table of the methods' stage lists is each method's real
list."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from policies.registry import build_policy

pytestmark = pytest.mark.integration

DOC = Path(__file__).resolve().parents[3] / "docs" / "explanation" / "architecture.md"
ROW = re.compile(r"^\| (`[^|]+`) \| `[^|]+` \| ([^|]+) \|$")


def _table() -> dict[str, list[str]]:
    """Method name -> the stage names its row lists (bold and remarks dropped)."""
    rows = {}
    for line in DOC.read_text().splitlines():
        match = ROW.match(line)
        if match is None:
            continue
        stages = re.sub(r"\(.*\)", "", match.group(2)).replace("*", "")
        names = [name.strip() for name in stages.split(",") if name.strip()]
        for method in re.findall(r"`([^`]+)`", match.group(1)):
            rows[method] = names
    return rows


TABLE = _table()


def test_the_table_lists_the_learned_methods():
    assert {"riskflow", "riskflow-raw", "strive", "bits", "bits-raw", "ctg"} <= set(TABLE)


@pytest.mark.parametrize("method", sorted(TABLE))
def test_each_row_is_the_methods_stage_list(method):
    policy = build_policy(method, {}, k=5, planning_interval=0.5, target="others", seed=0)
    assert [stage.__name__ for stage in policy.stages] == TABLE[method]
