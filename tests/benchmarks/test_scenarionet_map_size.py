"""benchmarks/scenarionet_map_size.py end to end at its smallest size."""

from __future__ import annotations

from tests.benchmarks.scripts import load_benchmark


def test_prints_the_whole_and_the_cropped_row(capsys):
    bench = load_benchmark("scenarionet_map_size")
    bench.main(["--area", "600", "--repeats", "1", "--vehicles", "5"])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:3] == ["scene", "crop", "raster"]
    whole, cropped = lines[1:3]
    assert "synthetic 600 m city" in whole and " False " in whole
    assert " True " in cropped and "x smaller" in cropped
