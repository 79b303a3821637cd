"""A ScenarioNet dataset folder as a lazy source: opening vs loading every scene, map cache.

The scenes of ``--data`` (a ScenarioNet dataset folder) are written ``--copies`` times each,
with distinct scenario ids (so distinct file contents), into a temporary dataset folder of
N = copies x scenes files, in ScenarioNet's layout (``dataset_summary.pkl``,
``dataset_mapping.pkl``, the files in one sub-folder). Two tables:

1. Opening the folder (:class:`~riskflow_env.scenarios.scenarionet_dataset.
   ScenarioNetDataset`: the index files only) against loading all N scenes into a list,
   with the converted-map cache empty (every map built and written) and full (every map
   read back); the memory column is the arrays held (tracks, masks, map rasters). A
   last row opens an index of ``--index-scenes`` entries (no scene files behind it).
2. Per scene of ``--data``: building its map (cache miss: build + write) against reading
   it back (hit), cropped (the default) and the whole recording area (``crop=False``);
   medians of ``--repeats`` loads, each with a fresh cache for the misses.

    python benchmarks/scenarionet_dataset.py --data sd_nuscenes_mini [--copies 25]
"""

from __future__ import annotations

import pickle
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from policies.dataclass_cli import check_at_least, parse_dataclass
from riskflow_env.cli_errors import run_script
from riskflow_env.scenarios.map_cache import MapCache
from riskflow_env.scenarios.safe_pickle import load_data_pickle
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.scenarios.scenarionet import load_scenarionet
from riskflow_env.scenarios.scenarionet_dataset import MAPPING_FILE, SUMMARY_FILE
from riskflow_env.scenarios.scenarionet_dataset import ScenarioNetDataset as Dataset


@dataclass(frozen=True)
class Options:
    """Benchmark options."""

    data: str
    """a ScenarioNet dataset folder whose scenes are replicated"""
    copies: int = 25
    """copies of each scene in the timed dataset"""
    repeats: int = 3
    """timed loads per row of the per-scene table (the median is reported)"""
    index_scenes: int = 5000
    """summary entries of the index-only dataset whose opening is timed too (0: none)"""

    def __post_init__(self) -> None:
        check_at_least(self, {"copies": 1, "repeats": 1, "index_scenes": 0})


def replicate(source: Dataset, copies: int, folder: Path) -> None:
    """``copies`` copies of every scene of ``source``, ids suffixed ``-c<k>``, as a dataset."""
    summary, mapping, sub = {}, {}, folder / f"{folder.name}_0"
    sub.mkdir(parents=True)
    for index in range(len(source)):
        description = load_data_pickle(source.path(index))
        metadata = description["metadata"]
        base = str(metadata.get("scenario_id", metadata.get("id", index)))
        for copy in range(copies):
            scene_id = f"{base}-c{copy}"
            description["id"] = metadata["id"] = metadata["scenario_id"] = scene_id
            name = f"sd_bench_v0_{scene_id}.pkl"
            (sub / name).write_bytes(pickle.dumps(description))
            summary[name], mapping[name] = pickle.loads(pickle.dumps(metadata)), sub.name
    (folder / SUMMARY_FILE).write_bytes(pickle.dumps(summary))
    (folder / MAPPING_FILE).write_bytes(pickle.dumps(mapping))


def index_only(source: Dataset, scenes: int, folder: Path) -> None:
    """A dataset index of ``scenes`` entries (each a copy of a ``source`` scene's
    metadata), without the scenario files: what opening costs at that size."""
    metadata = [load_data_pickle(source.path(i))["metadata"] for i in range(len(source))]
    summary = {
        f"sd_bench_v0_{k}.pkl": pickle.loads(pickle.dumps(metadata[k % len(metadata)]))
        for k in range(scenes)
    }
    folder.mkdir(parents=True)
    (folder / SUMMARY_FILE).write_bytes(pickle.dumps(summary))
    (folder / MAPPING_FILE).write_bytes(pickle.dumps(dict.fromkeys(summary, "")))


def held_mb(scenes: list[Scenario]) -> float:
    """[MB] arrays held by ``scenes`` (tracks, masks, map rasters)."""
    total = sum(s.states.nbytes + s.valid.nbytes + s.map.drivable.nbytes + s.map.sdf.nbytes
                for s in scenes)  # fmt: skip
    return total / 2**20


def open_vs_load(folder: Path, cache_dir: Path) -> list[tuple[str, float, float]]:
    """(what, seconds, MB held) of opening ``folder`` and of loading all its scenes."""
    start = time.perf_counter()
    dataset = Dataset(folder, map_cache=MapCache(cache_dir), keep=0)
    rows = [(f"open ({len(dataset)} scenes, index files only)", time.perf_counter() - start, 0.0)]
    for state in ("empty: every map built", "full: every map read"):
        start = time.perf_counter()
        scenes = [dataset.load(i) for i in range(len(dataset))]
        rows.append((f"load all, map cache {state}", time.perf_counter() - start, held_mb(scenes)))
    return rows


def miss_vs_hit(path: Path, crop: bool, repeats: int, root: Path) -> tuple[float, float, float]:
    """Median seconds of a load that builds the map (miss), one that reads it (hit), and
    the cached file's size [MB]."""
    misses, hits = [], []
    for repeat in range(repeats):
        cache = MapCache(root / f"{path.stem}-{crop}-{repeat}")
        for times in (misses, hits):
            start = time.perf_counter()
            load_scenarionet(path, crop=crop, map_cache=cache)
            times.append(time.perf_counter() - start)
    size = sum(p.stat().st_size for p in cache.folder.glob("*.npz")) / 2**20
    return statistics.median(misses), statistics.median(hits), size


PROG = "scenarionet_dataset.py"  # the name in usage and error lines


def main(argv: list[str] | None = None) -> None:
    """Print both tables."""
    options = parse_dataclass(Options, argv, PROG, __doc__.split("\n")[0], debug=True)
    source = Dataset(options.data, map_cache=False)
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(scratch)
        replicate(source, options.copies, root / "sd_bench")
        print(f"{len(source)} scenes x {options.copies} copies")
        rows = open_vs_load(root / "sd_bench", root / "maps")
        peer = rows[1][1]  # loading every scene, every map built: the peer
        print("| | time [s] | / loading all | arrays held [MB] |\n|---|---|---|---|")
        for what, seconds, held in rows:
            print(f"| {what} | {seconds:.3f} | {seconds / peer:.3f} | {held:.1f} |")
        if options.index_scenes:
            index_only(source, options.index_scenes, root / "sd_index")
            start = time.perf_counter()
            Dataset(root / "sd_index", map_cache=False)
            seconds = time.perf_counter() - start
            size = (root / "sd_index" / SUMMARY_FILE).stat().st_size / 2**20
            what = f"open {options.index_scenes} scenes ({size:.0f} MB summary)"
            print(f"| {what} | {seconds:.3f} | | |")
        print(
            "\n| scene | crop | miss: build + write [s] | hit: read [s] | miss / hit "
            "| cached map [MB] |\n|---|---|---|---|---|---|"
        )
        for index in range(len(source)):
            for crop in (True, False):
                miss, hit, size = miss_vs_hit(source.path(index), crop, options.repeats, root)
                name = source.names[index]
                print(f"| {name} | {crop} | {miss:.3f} | {hit:.3f} | {miss / hit:.1f} "
                      f"| {size:.2f} |")  # fmt: skip


if __name__ == "__main__":
    run_script(PROG, main)
