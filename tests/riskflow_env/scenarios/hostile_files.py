"""Shared by the hostile-file tests of the loaders (test_hostile_pickles2.py,
test_hostile_scenarionet.py): a small file written in the test, read in a capped child
process (:mod:`tests.capped`), refused with a short message naming what it must, or
loaded, within the CPU-time and memory bounds."""

from __future__ import annotations

from pathlib import Path

from tests.capped import Outcome, assert_bounded, run_capped

SETUP = (
    "from riskflow_env.scenarios.safe_pickle import load_data_pickle\n"
    "from riskflow_env.scenarios.scenarionet import load_scenarionet\n"
    "from riskflow_env.scenarios.scenarionet_dataset import ScenarioNetDataset"
)


def refused(outcome: Outcome, *fragments: str, error: str = "ValueError") -> None:
    """``error`` whose short message holds every fragment, within a CPU-time bound and 500 MB."""
    assert outcome.error == error, outcome
    assert outcome.chars < 1000, outcome
    for fragment in fragments:
        assert fragment in outcome.message, (fragment, outcome.message)
    assert_bounded(outcome)


def loaded(outcome: Outcome) -> None:
    assert outcome.error is None, outcome
    assert_bounded(outcome)


def run(path: Path, loader: str = "load_data_pickle", args: str = "", tail: str = "") -> Outcome:
    return run_capped(SETUP, f"{loader}({str(path)!r}{args}){tail}")


def write(tmp_path: Path, name: str, data: bytes) -> Path:
    path = tmp_path / name
    path.write_bytes(data)
    assert path.stat().st_size < 2 * 2**20
    return path
