"""benchmarks/scenarionet_dataset.py end to end at its smallest size, on toy scenes written
as ScenarioNet writes a dataset folder."""

from __future__ import annotations

from tests.benchmarks.scripts import load_benchmark
from tests.riskflow_env.scenarios.scenarionet_datasets import toy_descriptions, write_dataset


def test_prints_both_tables(tmp_path, capsys):
    folder = tmp_path / "sd_toy"
    write_dataset(folder, toy_descriptions(2))
    bench = load_benchmark("scenarionet_dataset")
    bench.main(["--data", str(folder), "--copies", "1", "--repeats", "1", "--index-scenes", "10"])
    out = capsys.readouterr().out
    assert "2 scenes x 1 copies" in out and "open (2 scenes, index files only)" in out
    assert "load all, map cache empty" in out and "| open 10 scenes" in out
    assert out.count("| True |") == 2 and out.count("| False |") == 2  # both crops per scene
