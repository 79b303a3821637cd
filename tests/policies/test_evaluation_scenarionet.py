"""riskflow-eval --data on a ScenarioNet dataset folder: scenes read when a rollout needs
them, the same numbers with any worker count, errors naming --data; on the real nuScenes
samples the realism metrics rank log replay over the generator over the adversary."""

from __future__ import annotations

import math
import pickle

import pytest

from policies.evaluation import EvalOptions, ResultsStore, build_tables, run_evaluation
from policies.evaluation.cli import main
from riskflow_env.user_cache import CACHE_ENV
from tests.riskflow_env.scenarios.scenarionet_datasets import (
    MAPPING,
    toy_descriptions,
    write_dataset,
)
from tests.samples import SCENARIONET_DIR, require_samples


def _options(data, out, **changes) -> EvalOptions:
    fields = dict(methods=("idm", "replay"), scenes=2, duration=1.0, wosac=False, report=False)
    return EvalOptions(data=str(data), out=str(out), **(fields | changes))


def _numbers(out) -> dict[str, dict]:
    rows = ResultsStore(out).rows()
    return {row["key"]: {k: v for k, v in row.items() if k not in ("timing", "samples")}
            for row in rows}  # fmt: skip


def test_eval_reads_only_the_scenes_it_runs(scenarionet_toy, tmp_path):
    summary = run_evaluation(_options(scenarionet_toy, tmp_path / "one"), progress=False)
    assert summary["ran"] == 4
    rows = ResultsStore(tmp_path / "one").rows()
    assert {row["scene"] for row in rows} == {
        "scenarionet/nuscenes-toy-0",
        "scenarionet/nuscenes-toy-1",
    }
    maps = list((tmp_path / "user-cache" / "maps").glob("*.npz"))
    assert len(maps) == 2  # the third scene was never read
    run_evaluation(_options(scenarionet_toy, tmp_path / "two", workers=2), progress=False)
    assert _numbers(tmp_path / "two") == _numbers(tmp_path / "one")


@pytest.mark.reliability
def test_bad_dataset_folders_name_the_argument(scenarionet_toy, tmp_path, capsys):
    out = tmp_path / "out"
    (scenarionet_toy / MAPPING).write_bytes(pickle.dumps({"sd_x.pkl": ""}))
    with pytest.raises(SystemExit):
        main(["--data", str(scenarionet_toy), "--methods", "idm", "--out", str(out)])
    error = capsys.readouterr().err
    missing = "no entry for sd_nuscenes_v1.0-mini_nuscenes-toy-0.pkl"
    assert f"--data: {scenarionet_toy / MAPPING}: {missing}" in error
    write_dataset(tmp_path / "sd_other", toy_descriptions(2))
    next((tmp_path / "sd_other").glob("*/*toy-1.pkl")).unlink()
    with pytest.raises(SystemExit):
        main(["--data", str(tmp_path / "sd_other"), "--methods", "idm", "--out", str(out)])
    error = capsys.readouterr().err
    assert "--data: 1 scenario file(s) missing, e.g." in error and "toy-1.pkl" in error
    assert not out.exists()


@pytest.mark.slow  # 10 s rollouts of three methods on every real sample: about 20 s of CPU
def test_realism_on_real_samples_replay_nearest_the_log_the_generators_close_to_it(
    tmp_path, monkeypatch
):
    """On the real nuScenes samples (10 s, IDM ego, one seed): log replay is nearest the log
    by ADE and KDD; the unguided generator scores within 0.05 of it by WOSAC-style (the
    replayed vehicles do not react to the IDM ego, the generated ones do), and the RiskFlow
    adversary attacking the ego within 0.08 of the generator, moving its vehicles off the
    log no less. Measured at seed 0: WOSAC 0.857 / 0.822 / 0.822, ADE 0.06 / 2.15 / 2.32 m,
    KDD 2.13 / 2.64 / 2.64; at seeds 1 and 2 both generators score above replay by WOSAC
    (0.858-0.861 against 0.857), so no order of the three by WOSAC holds on four
    rollouts. A later machine, with the same code, gave the adversary 0.795 at seed 0 (the
    generator 0.822), with the torch reference loops too and with older numpy, scipy,
    shapely and numba alike: four attacked rollouts move that much. With the turning
    radius in the dynamics the generator rose to 0.859 and the adversary stayed at 0.794.
    Replay is a reference: outside the RS normalisation, which compares the two
    generators."""
    require_samples()
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "user-cache"))
    options = EvalOptions(
        data=str(SCENARIONET_DIR), methods=("replay", "bits", "riskflow"), k=("5",),
        seeds=(0,), duration=10.0, target="ego", out=str(tmp_path / "eval"), report=False,
    )  # fmt: skip
    run_evaluation(options, progress=False)
    (table,) = build_tables(ResultsStore(tmp_path / "eval"))
    metrics = table.metrics
    replay, generator, adversary = (metrics[m] for m in ("replay", "bits", "riskflow"))
    assert math.isnan(replay["rs"]) and math.isnan(replay["cs"])  # a reference
    assert replay["kdd"] < min(generator["kdd"], adversary["kdd"])
    assert replay["ade"] < 0.5 < generator["ade"] < adversary["ade"]
    assert abs(generator["wosac"] - replay["wosac"]) < 0.05
    assert abs(adversary["wosac"] - generator["wosac"]) < 0.08
    # One attacker against the IDM ego does not reach it on these four short scenes
    # (ego collisions 0 of 4 for both); the adversary only moves its vehicles off the log.
    assert adversary["ego_collision_rate"] >= generator["ego_collision_rate"]
