"""A ScenarioNet dataset folder as a lazy scenario source (issue 14, deliverable 2).

Folders are written by test code in ScenarioNet's exact form
(tests/riskflow_env/scenarios/scenarionet_datasets.py); the real nuScenes samples are
used when present (tests/samples.py).
"""

from __future__ import annotations

import pickle
import shutil

import numpy as np
import pytest

import riskflow_env
from riskflow_env.scenarios import scenarionet, smoothing
from riskflow_env.scenarios.folders import open_scenes
from riskflow_env.scenarios.map_cache import MapCache
from riskflow_env.scenarios.scenarionet import load_scenarionet
from riskflow_env.scenarios.scenarionet_dataset import ScenarioNetDataset, is_scenarionet_folder
from riskflow_env.scenarios.sources import ScenarioBank
from riskflow_env.user_cache import CACHE_ENV
from tests.riskflow_env.scenarios.scenarionet_datasets import (
    MAPPING,
    SUMMARY,
    toy_descriptions,
    write_dataset,
)
from tests.samples import SCENARIONET_DIR

SAMPLES = sorted(SCENARIONET_DIR.glob("*.pkl")) if SCENARIONET_DIR.is_dir() else []


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    """A 3-scene nuScenes-form dataset written by 2 converter workers."""
    folder = tmp_path_factory.mktemp("datasets") / "sd_toy"
    write_dataset(folder, toy_descriptions(3))
    return folder


@pytest.fixture
def cache(tmp_path):
    return MapCache(tmp_path / "map-cache")


def _dataset(folder, cache, **options):
    return ScenarioNetDataset(folder, map_cache=cache, **options)


def _copy(toy, tmp_path):
    return shutil.copytree(toy, tmp_path / "copy")


def test_opening_reads_the_index_only(toy, cache, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("a scene was loaded while opening the folder")

    monkeypatch.setattr("riskflow_env.scenarios.scenarionet_dataset.load_scenarionet", refuse)
    dataset = _dataset(toy, cache)
    assert len(dataset) == 3
    assert dataset.names == tuple(f"scenarionet/nuscenes-toy-{k}" for k in range(3))
    assert dataset.folders == ("sd_toy_0", "sd_toy_1", "sd_toy_1")  # worker sub-folders
    assert dataset.path(2) == toy / "sd_toy_1" / "sd_nuscenes_v1.0-mini_nuscenes-toy-2.pkl"
    assert dataset.summaries[0]["sdc_id"] == "ego"
    assert dataset.missing_files() == []
    assert cache.hits == cache.misses == 0


def test_scenes_load_when_drawn_as_the_single_file_loader_loads_them(toy, cache):
    dataset = _dataset(toy, cache, keep=2)
    for index in range(len(dataset)):
        scenario = dataset[index]
        alone = load_scenarionet(dataset.path(index))
        assert scenario.name == alone.name == dataset.names[index]
        np.testing.assert_array_equal(scenario.states, alone.states)
        np.testing.assert_array_equal(scenario.valid, alone.valid)
        np.testing.assert_array_equal(scenario.map.drivable, alone.map.drivable)
    assert dataset[2] is dataset[2]  # kept in memory
    assert len(dataset._loaded) == 2  # no more than ``keep``
    with pytest.raises(IndexError, match="out of range for 3 scenes"):
        dataset[3]
    assert dataset[-1].name == dataset.names[2]


def test_draws_follow_the_env_seed(toy, cache):
    def drawn(seed: int) -> list[str]:
        env = riskflow_env.parallel_env(scenarios=_dataset(toy, cache))
        names = []
        for episode in range(6):
            env.reset(seed=seed + 1000 * episode)
            names.append(env.scenario.name)
        return names

    first = drawn(0)
    assert drawn(0) == first
    assert set(first) <= set(_dataset(toy, cache).names)
    assert drawn(1) != first or drawn(2) != first
    rng = np.random.default_rng(7)
    expected = [_dataset(toy, cache).names[int(rng.integers(3))] for _ in range(5)]
    rng, dataset = np.random.default_rng(7), _dataset(toy, cache)
    assert [dataset.sample(rng).name for _ in range(5)] == expected


def test_parallel_env_takes_the_folder(toy, monkeypatch, tmp_path):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "user-cache"))
    env = riskflow_env.parallel_env(scenarios=str(toy))
    assert isinstance(env.source, ScenarioNetDataset)
    observations, _ = env.reset(seed=0)
    assert "ego" in observations and env.scenario.name.startswith("scenarionet/nuscenes-toy-")
    assert any((tmp_path / "user-cache" / "maps").glob("*.npz"))  # the default map cache
    assert isinstance(open_scenes(toy), ScenarioNetDataset)
    assert isinstance(open_scenes(riskflow_env.scenarios.io.ASSETS / "eval"), ScenarioBank)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no scenes in .*empty: expected a folder of .npz"):
        open_scenes(tmp_path / "empty")
    (tmp_path / "notes.md").write_text("not a folder")
    with pytest.raises(NotADirectoryError, match="notes.md is a file; expected a folder of"):
        open_scenes(tmp_path / "notes.md")  # one file where the folder goes names the kinds


def test_second_load_hits_the_map_cache(toy, cache, monkeypatch):
    built = _dataset(toy, cache).load(0)
    assert (cache.hits, cache.misses) == (0, 1)
    assert len(list(cache.folder.glob("*.npz"))) == 1

    def refuse(*args, **kwargs):
        raise AssertionError("the map was built again")

    monkeypatch.setattr(scenarionet, "build_map", refuse)
    again = _dataset(toy, cache).load(0)  # a new dataset object: the cache is on disk
    assert (cache.hits, cache.misses) == (1, 1)
    np.testing.assert_array_equal(again.map.drivable, built.map.drivable)
    np.testing.assert_allclose(again.map.sdf, built.map.sdf, atol=1e-6)
    np.testing.assert_array_equal(again.map.origin, built.map.origin)
    assert [lane.lane_id for lane in again.map.lanes] == [lane.lane_id for lane in built.map.lanes]
    assert again.map.name == built.map.name and again.map.resolution == built.map.resolution
    with pytest.raises(ValueError, match="built again"):
        _dataset(toy, cache, resolution=1.0).load(0)  # other settings: another key


def test_map_cache_key_is_the_file_content(toy, cache, tmp_path):
    copy = _copy(toy, tmp_path)
    _dataset(toy, cache).load(1)
    _dataset(copy, cache).load(1)  # same bytes elsewhere: a hit
    assert (cache.hits, cache.misses) == (1, 1)
    path = _dataset(copy, cache).path(1)
    data = pickle.loads(path.read_bytes())
    data["map_features"].pop(next(iter(data["map_features"])))
    path.write_bytes(pickle.dumps(data))
    _dataset(copy, cache).load(1)  # edited file: a miss
    assert (cache.hits, cache.misses) == (1, 2)


def test_map_cache_writes_atomically_with_concurrent_writers(toy, cache):
    from concurrent.futures import ThreadPoolExecutor

    scene = _dataset(toy, cache).load(0)
    key = MapCache.key("0" * 64, test="concurrent")
    caches = [MapCache(cache.folder) for _ in range(6)]
    with ThreadPoolExecutor(6) as pool:
        maps = list(pool.map(lambda c: c.get_or_build(key, lambda: scene.map), caches))
    assert all(m.shape == scene.map.shape for m in maps)
    assert not list(cache.folder.glob(".*.tmp"))  # no temporary file left behind
    again = MapCache(cache.folder)
    np.testing.assert_array_equal(again.get_or_build(key, None).drivable, scene.map.drivable)
    assert again.hits == 1


def test_a_damaged_cache_file_is_rebuilt(toy, cache):
    _dataset(toy, cache).load(0)
    (damaged,) = cache.folder.glob("*.npz")
    damaged.write_bytes(b"not a zip file")
    with pytest.warns(UserWarning, match="rebuilding unreadable"):
        _dataset(toy, cache).load(0)
    assert cache.misses == 2
    assert _dataset(toy, cache).load(0) is not None and cache.hits == 1


def test_subset_and_pickling(toy, cache):
    dataset = _dataset(toy, cache)
    part = dataset.subset([2, 0])
    assert part.names == (dataset.names[2], dataset.names[0]) and len(part) == 2
    assert part[0].name == dataset.names[2]
    restored = pickle.loads(pickle.dumps(part))
    assert restored.names == part.names and not restored._loaded
    assert len(dataset.fingerprint()) == 1 + len(dataset)
    with pytest.raises(ValueError, match="at least one scene"):
        dataset.subset([])


def test_fingerprint_follows_the_smoothing_filter(toy, cache, monkeypatch):
    """Caches cut from smoothed scenes are rebuilt when the filter changes; others stay."""
    plain, smoothed = _dataset(toy, cache), _dataset(toy, cache, smooth=True)
    before = (plain.fingerprint(), smoothed.fingerprint())
    monkeypatch.setattr(smoothing, "VERSION", smoothing.VERSION + 1)
    assert plain.fingerprint() == before[0] and smoothed.fingerprint() != before[1]


def test_scenarionet_reader_fallbacks(toy, cache, tmp_path):
    """As ScenarioNet's ``read_dataset_summary``: without the mapping every file lies next
    to the summary; without the summary the folder's scenario files, sorted."""
    flat = tmp_path / "flat"
    flat.mkdir()
    for path in sorted(toy.glob("*/*.pkl")):
        if path.name.startswith("sd_"):
            shutil.copy(path, flat / path.name)
    assert is_scenarionet_folder(flat)
    listed = _dataset(flat, cache)
    assert listed.files == tuple(sorted(p.name for p in flat.iterdir()))
    assert listed.names == tuple(f"scenarionet/{name[:-4]}" for name in listed.files)
    assert listed[0].name == listed.names[0]  # the file name, as the summary gives no id
    shutil.copy(toy / SUMMARY, flat / SUMMARY)
    indexed = _dataset(flat, cache)  # a summary and no mapping
    assert indexed.names == _dataset(toy, cache).names and set(indexed.folders) == {""}


def _rewrite(folder, name, value):
    (folder / name).write_bytes(pickle.dumps(value))


@pytest.mark.parametrize(
    ("file", "value", "message"),
    [
        (SUMMARY, [1, 2], r"dataset_summary.pkl: expected a dict .* got list"),
        (SUMMARY, {}, r"dataset_summary.pkl: expected a dict .* got an empty dict"),
        (SUMMARY, {"../evil.pkl": {}}, r"dataset_summary.pkl: entry '../evil.pkl' is not"),
        (SUMMARY, {"sd_a.txt": {}}, r"dataset_summary.pkl: entry 'sd_a.txt' is not"),
        (SUMMARY, {"sd_a.pkl": [1]}, r"dataset_summary.pkl: the metadata of sd_a.pkl must be"),
        (MAPPING, "folder", r"dataset_mapping.pkl: expected a dict .* got str"),
        (MAPPING, {}, r"dataset_mapping.pkl: no entry for sd_nuscenes_v1.0-mini_nuscenes-toy"),
        (MAPPING, "absolute", r"dataset_mapping.pkl: the folder of .* must be a relative path"),
    ],
)
def test_bad_index_files_name_the_file(toy, tmp_path, file, value, message):
    copy = _copy(toy, tmp_path)
    if value == "absolute":
        value = dict.fromkeys(pickle.loads((toy / SUMMARY).read_bytes()), str(copy))
    _rewrite(copy, file, value)
    with pytest.raises(ValueError, match=message):
        ScenarioNetDataset(copy, map_cache=False)


def test_hostile_index_file_is_refused_without_running_it(toy, tmp_path):
    copy = _copy(toy, tmp_path)
    (copy / MAPPING).write_bytes(b"cos\nsystem\n(S'touch /tmp/riskflow_hostile_marker'\ntR.")
    with pytest.raises(ValueError, match=r"dataset_mapping.pkl: refusing .* 'os.system'"):
        ScenarioNetDataset(copy, map_cache=False)


def test_bad_folders_and_scene_files_name_the_path(toy, tmp_path):
    with pytest.raises(FileNotFoundError, match="folder .*nowhere does not exist"):
        ScenarioNetDataset(tmp_path / "nowhere")
    with pytest.raises(NotADirectoryError, match="is a file, not a ScenarioNet dataset folder"):
        ScenarioNetDataset(toy / SUMMARY)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no dataset_summary.pkl and no scenario files"):
        ScenarioNetDataset(tmp_path / "empty")
    with pytest.raises(ValueError, match="keep must be an int >= 0"):
        ScenarioNetDataset(toy, keep=-1)
    with pytest.raises(TypeError, match=r"unknown option\(s\) \['smoth'\]; .* smooth"):
        ScenarioNetDataset(toy, smoth=True)
    copy = _copy(toy, tmp_path)
    dataset = ScenarioNetDataset(copy, map_cache=False)  # opens: scene files are not read
    dataset.path(0).unlink()
    dataset.path(1).write_bytes(b"\x80\x04garbage")
    assert dataset.missing_files() == [dataset.path(0)]
    with pytest.raises(FileNotFoundError, match=r"toy-0.pkl: listed in .*dataset_summary.pkl"):
        dataset[0]
    with pytest.raises(FileNotFoundError, match=r"toy-0.pkl: listed in"):
        dataset.fingerprint()
    with pytest.raises(ValueError, match=r"sd_nuscenes_v1.0-mini_nuscenes-toy-1.pkl: not a"):
        dataset[1]
    assert dataset[2].name == dataset.names[2]  # the other scenes still load


def test_real_samples_as_a_dataset(tmp_path, cache):
    """The four nuScenes samples written as ScenarioNet's converter writes them (optional:
    skipped without ../shared/data/scenarionet)."""
    if not SAMPLES:
        pytest.skip(f"no ScenarioNet samples in {SCENARIONET_DIR}")
    folder = tmp_path / "sd_nuscenes_mini"
    write_dataset(folder, SAMPLES, workers=2)
    dataset = _dataset(folder, cache)
    assert dataset.names == tuple(
        f"scenarionet/{path.name.split('_')[-1][:-4]}" for path in SAMPLES
    )
    for index, path in enumerate(SAMPLES):
        scenario, alone = dataset.load(index), load_scenarionet(path)
        assert scenario.name == alone.name
        np.testing.assert_array_equal(scenario.states, alone.states)
    assert (cache.hits, cache.misses) == (0, len(SAMPLES))
    again = _dataset(folder, cache).load(0)
    assert cache.hits == 1
    np.testing.assert_array_equal(again.map.drivable, load_scenarionet(SAMPLES[0]).map.drivable)


def test_a_rollout_does_not_depend_on_the_cache_state(toy, cache):
    """The cached map holds the built map's arrays bit for bit (lanes, raster, SDF): the
    same seed gives the same rollout from a built map and from a cached one."""
    built = _dataset(toy, cache).load(1)  # miss: built (and written)
    cached = _dataset(toy, cache).load(1)  # hit: read back
    assert cache.hits == 1
    np.testing.assert_array_equal(cached.map.sdf, built.map.sdf)
    for lane_a, lane_b in zip(built.map.lanes, cached.map.lanes, strict=True):
        np.testing.assert_array_equal(lane_a.centerline, lane_b.centerline)
        assert (lane_a.width, lane_a.successors) == (lane_b.width, lane_b.successors)

    def rollout(scenario) -> list[np.ndarray]:
        env = riskflow_env.parallel_env(scenarios=scenario)
        observations, _ = env.reset(seed=3)
        trace = [observations["ego"]]
        for step in range(15):
            actions = {agent: np.array([0.5, 0.05 * (step % 3 - 1)]) for agent in env.agents}
            observations, *_ = env.step(actions)
            trace += [observations[agent] for agent in sorted(observations)]
        return trace

    for a, b in zip(rollout(built), rollout(cached), strict=True):
        np.testing.assert_array_equal(a, b)
