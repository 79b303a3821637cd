"""riskflow-eval --data on a ScenarioNet dataset folder: scenes read when a rollout needs
them, the same numbers with any worker count, errors naming --data."""

from __future__ import annotations

import pickle

import pytest

from policies.evaluation import EvalOptions, ResultsStore, run_evaluation
from policies.evaluation.cli import main
from riskflow_env.user_cache import CACHE_ENV
from tests.riskflow_env.scenarios.scenarionet_datasets import (
    MAPPING,
    toy_descriptions,
    write_dataset,
)


@pytest.fixture
def toy(tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "user-cache"))
    folder = tmp_path / "sd_toy"
    write_dataset(folder, toy_descriptions(3))
    return folder


def _options(data, out, **changes) -> EvalOptions:
    fields = dict(methods=("idm", "replay"), scenes=2, duration=1.0, wosac=False, report=False)
    return EvalOptions(data=str(data), out=str(out), **(fields | changes))


def _numbers(out) -> dict[str, dict]:
    rows = ResultsStore(out).rows()
    return {row["key"]: {k: v for k, v in row.items() if k not in ("timing", "samples")}
            for row in rows}  # fmt: skip


def test_eval_reads_only_the_scenes_it_runs(toy, tmp_path):
    summary = run_evaluation(_options(toy, tmp_path / "one"), progress=False)
    assert summary["ran"] == 4
    rows = ResultsStore(tmp_path / "one").rows()
    assert {row["scene"] for row in rows} == {
        "scenarionet/nuscenes-toy-0",
        "scenarionet/nuscenes-toy-1",
    }
    maps = list((tmp_path / "user-cache" / "maps").glob("*.npz"))
    assert len(maps) == 2  # the third scene was never read
    run_evaluation(_options(toy, tmp_path / "two", workers=2), progress=False)
    assert _numbers(tmp_path / "two") == _numbers(tmp_path / "one")


@pytest.mark.reliability
def test_bad_dataset_folders_name_the_argument(toy, tmp_path, capsys):
    out = tmp_path / "out"
    (toy / MAPPING).write_bytes(pickle.dumps({"sd_x.pkl": ""}))
    with pytest.raises(SystemExit):
        main(["--data", str(toy), "--methods", "idm", "--out", str(out)])
    error = capsys.readouterr().err
    assert (
        f"--data: {toy / MAPPING}: no entry for sd_nuscenes_v1.0-mini_nuscenes-toy-0.pkl" in error
    )
    write_dataset(tmp_path / "sd_other", toy_descriptions(2))
    next((tmp_path / "sd_other").glob("*/*toy-1.pkl")).unlink()
    with pytest.raises(SystemExit):
        main(["--data", str(tmp_path / "sd_other"), "--methods", "idm", "--out", str(out)])
    error = capsys.readouterr().err
    assert "--data: 1 scenario file(s) missing, e.g." in error and "toy-1.pkl" in error
    assert not out.exists()
