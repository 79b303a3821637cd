"""riskflow-eval's report over methods that ran different scenes."""

from __future__ import annotations

from dataclasses import replace

import pytest

from policies.evaluation import ResultsStore, build_tables, run_evaluation, write_report
from tests.policies.test_evaluation import TINY


def test_a_method_run_on_fewer_scenes_narrows_the_table_and_says_so(tmp_path):
    """An extension run on fewer scenes: the table compares the scenes every method ran and
    counts the rollouts it leaves out (it dropped them without a word)."""
    out = tmp_path / "extended"
    run_evaluation(replace(TINY, out=str(out), methods=("idm",)), progress=False)
    run_evaluation(replace(TINY, out=str(out), methods=("replay",), scenes=1), progress=False)
    (table,) = build_tables(ResultsStore(out))
    assert table.scenes == 1 and table.left_out == {"idm": 1}
    text = write_report(out, plots=False).read_text()
    assert "rollouts left out (in results.jsonl still): idm 1." in text


def test_a_report_of_a_folder_that_is_not_there_says_so(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such folder"):
        write_report(tmp_path / "nofolder")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no results"):
        write_report(tmp_path / "empty")
