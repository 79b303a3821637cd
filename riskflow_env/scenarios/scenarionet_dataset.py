"""A whole ScenarioNet dataset folder as a lazy scenario source.

ScenarioNet's converters (``python -m scenarionet.convert_<source> -d FOLDER``) and its
``merge`` / ``split`` / ``filter`` tools write a dataset as a folder holding

* ``dataset_summary.pkl``: a dict, scenario file name -> that scenario's ``metadata``
  (``id``, ``sdc_id``, ``object_summary``, ``number_summary``..., arrays stored as lists
  and sets as tuples), in the dataset's order;
* ``dataset_mapping.pkl``: a dict, scenario file name -> the folder that holds the
  file, relative to the dataset folder (``""``: next to the summary; ``"<name>_3"``: the
  sub-folder of converter worker 3; ``"../other_dataset"`` after a merge);
* the scenario files, ``sd_<dataset>_<version>_<scenario id>.pkl``.

:class:`ScenarioNetDataset` reads the two index files when it is opened, and nothing
else: a scene is read and converted (:func:`~riskflow_env.scenarios.scenarionet.
load_scenarionet`) when it is drawn or indexed, and the last few are kept in memory.
Its maps go through the disk cache of converted maps (:mod:`~riskflow_env.scenarios.
map_cache`), so a scene drawn again, in this process or any later one, skips the map
build. As ScenarioNet's own reader does, a missing ``dataset_mapping.pkl`` means every
file lies next to the summary, and a folder without ``dataset_summary.pkl`` lists its
scenario files (``sd_*.pkl`` or digits ``.pkl``, sorted by name). Both index files are read
with the restricted unpickler (:mod:`~riskflow_env.scenarios.safe_pickle`).

Scene names are ``"scenarionet/<scenario id>"`` from the summary (``scenario_id``, else
``id``), as :func:`load_scenarionet` names them, or ``"scenarionet/<file name>"`` (no
``.pkl``) where the summary gives no id or two files give the same one. An entry's
metadata holds at most :data:`MAX_METADATA_KEYS` keys (a summary that shares one huge
metadata dict among its entries would otherwise be copied once per entry), and its id is
a str or an int (:func:`~riskflow_env.untrusted.entry_id`); a scene file that
cannot be read is a ``ValueError`` naming it and the summary.
"""

from __future__ import annotations

import inspect
import os
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from riskflow_env.config import is_integer
from riskflow_env.scenarios import smoothing
from riskflow_env.scenarios.map_cache import MapCache
from riskflow_env.scenarios.safe_pickle import load_data_pickle
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.scenarios.scenarionet import load_scenarionet
from riskflow_env.untrusted import MAX_QUOTE, brief, entry_id

SUMMARY_FILE = "dataset_summary.pkl"
MAPPING_FILE = "dataset_mapping.pkl"
INDEX_FILES = (SUMMARY_FILE, MAPPING_FILE)
#: per-track and per-step summary entries not kept in memory (most of a summary's size:
#: about 75 KB of Python objects per nuScenes scene with them, a few KB without)
BULKY_METADATA = ("object_summary", "ts")
MAX_METADATA_KEYS = 1024  # keys of one entry's metadata (ScenarioNet writes 13)
MAX_FILE_NAME = 255  # [characters] of a scenario file name (the usual file-system limit)


def is_scenario_file(name: str) -> bool:
    """ScenarioNet's rule for a scenario file name: ``sd_*.pkl`` or digits ``.pkl``."""
    stem, suffix = os.path.splitext(name)
    return suffix == ".pkl" and name not in INDEX_FILES and (stem[:3] == "sd_" or stem.isdigit())


def is_scenarionet_folder(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder with ``dataset_summary.pkl``, or scenario files only."""
    path = Path(path)
    if not path.is_dir():
        return False
    if (path / SUMMARY_FILE).is_file():
        return True
    names = [entry.name for entry in os.scandir(path) if entry.is_file()]
    return any(map(is_scenario_file, names)) and not any(n.endswith(".npz") for n in names)


class ScenarioNetDataset:
    """The scenes of a ScenarioNet dataset folder, loaded when drawn (module docstring).

    Args:
        folder: the dataset folder (the one holding ``dataset_summary.pkl``).
        map_cache: the disk cache of converted maps: True (default) for the user cache's
            (:class:`~riskflow_env.scenarios.map_cache.MapCache`), a ``MapCache`` of
            your own, or False to build every map.
        keep: how many loaded scenes stay in memory (least recently used dropped), >= 0.
        **options: how each scene is loaded: the keyword arguments of
            :func:`~riskflow_env.scenarios.scenarionet.load_scenarionet` (``resolution``,
            ``current_index``, ``min_future_steps``, ``margin``, ``crop``,
            ``crop_margin``, ``smooth``), its defaults for those not given.

    Attributes:
        files, folders, names: per scene, in the summary's order: the file name, its
            folder relative to ``folder``, the scene name.
        summaries: per scene, the metadata the summary holds, without the per-track and
            per-step entries (:data:`BULKY_METADATA`): ``sdc_id``, ``number_summary``
            (counts of objects per type, moving objects...), the dataset's own fields.

    Raises:
        FileNotFoundError: ``folder`` does not exist, or holds neither
            ``dataset_summary.pkl`` nor scenario files.
        NotADirectoryError: ``folder`` is a file.
        ValueError: naming the file, when an index file is not what ScenarioNet writes
            (not a dict of file names, a file missing from the mapping, an absolute or
            malformed path) or is refused by the restricted unpickler.

    A scene file that is missing or malformed raises when that scene is loaded
    (``FileNotFoundError`` / ``ValueError`` naming the file); :meth:`missing_files`
    checks them all at once without reading them.
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        map_cache: MapCache | bool = True,
        keep: int = 4,
        **options: Any,
    ) -> None:
        folder = Path(folder)
        if folder.is_file():
            raise NotADirectoryError(
                f"{folder} is a file, not a ScenarioNet dataset folder (one holding "
                f"{SUMMARY_FILE} and {MAPPING_FILE}); load one scenario file with "
                "riskflow_env.scenarios.scenarionet.load_scenarionet"
            )
        if not folder.is_dir():
            raise FileNotFoundError(f"ScenarioNet dataset folder {folder} does not exist")
        if not is_integer(keep) or keep < 0:
            raise ValueError(f"keep must be an int >= 0 [scenes], got {keep!r}")
        if not isinstance(map_cache, (bool, MapCache)):
            raise TypeError(f"map_cache must be a bool or a MapCache, got {map_cache!r}")
        self.folder = folder
        self.options = _load_options(options)
        self.map_cache = MapCache() if map_cache is True else (map_cache or None)
        self.keep = int(keep)
        summary, mapping = read_index(folder)
        self.files = tuple(summary)
        self.summaries = tuple(
            {key: value for key, value in metadata.items() if key not in BULKY_METADATA}
            for metadata in summary.values()
        )
        self.folders = tuple(mapping[name] for name in self.files)
        self.names = _names(self.files, self.summaries, folder / SUMMARY_FILE)
        self._loaded: OrderedDict[int, Scenario] = OrderedDict()

    def __len__(self) -> int:
        return len(self.files)

    def __repr__(self) -> str:
        return f"ScenarioNetDataset({str(self.folder)!r}, {len(self)} scenes)"

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_loaded"] = OrderedDict()  # scenes are reloaded, not shipped to workers
        return state

    def path(self, index: int) -> Path:
        """The scenario file of scene ``index``."""
        index = self._index(index)
        return self.folder / self.folders[index] / self.files[index]

    def __getitem__(self, index: int) -> Scenario:
        """Scene ``index`` (read when not among the last ``keep`` scenes used)."""
        index = self._index(index)
        if index in self._loaded:
            self._loaded.move_to_end(index)
            return self._loaded[index]
        scenario = self.load(index)
        if self.keep:
            self._loaded[index] = scenario
            while len(self._loaded) > self.keep:
                self._loaded.popitem(last=False)
        return scenario

    def load(self, index: int) -> Scenario:
        """Scene ``index``, read from its file now (nothing kept in memory).

        Raises:
            FileNotFoundError: naming the file and the summary that lists it.
            ValueError: naming the file, when it is not a readable scenario.
        """
        index = self._index(index)
        path = self.path(index)
        if not path.is_file():
            raise FileNotFoundError(
                f"{path}: listed in {self.folder / SUMMARY_FILE} but there is no such file"
            )
        try:
            scenario = load_scenarionet(path, **self.options, map_cache=self.map_cache)
        except FileNotFoundError:
            raise
        except OSError as err:  # unreadable (permissions, a folder, an I/O error)
            raise ValueError(
                f"{path}: listed in {self.folder / SUMMARY_FILE} but cannot be read "
                f"({err.strerror or type(err).__name__})"
            ) from None
        if scenario.name != self.names[index]:
            scenario = replace(scenario, name=self.names[index])
        return scenario

    def sample(self, rng: np.random.Generator, max_agents: int | None = None) -> Scenario:
        """A uniformly drawn scene: a function of ``rng``'s state only (``max_agents`` is
        applied by the env at reset)."""
        return self[int(rng.integers(len(self)))]

    def subset(self, indices: Sequence[int]) -> ScenarioNetDataset:
        """The scenes ``indices`` (in that order) as a dataset of their own (same options
        and map cache; nothing is read)."""
        picked = [self._index(int(i)) for i in indices]
        if not picked:
            raise ValueError(f"{self.folder}: a subset needs at least one scene index")
        view = object.__new__(ScenarioNetDataset)
        view.__dict__.update(self.__dict__)
        view.files = tuple(self.files[i] for i in picked)
        view.summaries = tuple(self.summaries[i] for i in picked)
        view.folders = tuple(self.folders[i] for i in picked)
        view.names = tuple(self.names[i] for i in picked)
        view._loaded = OrderedDict()
        return view

    def missing_files(self) -> list[Path]:
        """The scenario files the index lists that do not exist (one ``stat`` each)."""
        return [path for path in map(self.path, range(len(self))) if not path.is_file()]

    def fingerprint(self) -> list[Any]:
        """What the scenes' content depends on: the load options and each file's
        (name, size, modification time); FileNotFoundError naming a missing file."""
        parts: list[Any] = [sorted((k, repr(v)) for k, v in self.options.items())]
        if self.options.get("smooth"):  # unsmoothed scenes keep their fingerprint
            parts.append(["smoothing", smoothing.VERSION])
        for index in range(len(self)):
            path = self.path(index)
            try:
                stat = path.stat()
            except FileNotFoundError:
                raise FileNotFoundError(
                    f"{path}: listed in {self.folder / SUMMARY_FILE} but there is no such file"
                ) from None
            parts.append([self.files[index], self.folders[index], stat.st_size, stat.st_mtime_ns])
        return parts

    def _index(self, index: int) -> int:
        if isinstance(index, (bool, np.bool_)) or not isinstance(index, (int, np.integer)):
            raise TypeError(f"scene index must be an int, got {type(index).__name__}")
        if not -len(self) <= index < len(self):
            raise IndexError(f"scene index {index} out of range for {len(self)} scenes")
        return int(index) % len(self)


def _load_options(options: dict[str, Any]) -> dict[str, Any]:
    """Every scene-loading option of :func:`load_scenarionet`, ``options`` over its
    defaults; TypeError naming an option it does not take."""
    signature = inspect.signature(load_scenarionet)
    taken = [name for name in signature.parameters if name not in ("path", "map_cache")]
    unknown = sorted(set(options) - set(taken))
    if unknown:
        raise TypeError(
            f"ScenarioNetDataset: unknown option(s) {unknown}; scenes are loaded with the "
            f"options of load_scenarionet: {', '.join(taken)}"
        )
    return {name: options.get(name, signature.parameters[name].default) for name in taken}


def read_index(folder: Path) -> tuple[dict[str, Mapping], dict[str, str]]:
    """(summary, mapping) of a dataset folder, checked (see :class:`ScenarioNetDataset`)."""
    summary_path, mapping_path = folder / SUMMARY_FILE, folder / MAPPING_FILE
    if summary_path.is_file():
        summary = load_data_pickle(summary_path)
        if not isinstance(summary, Mapping) or not summary:
            got = "an empty dict" if isinstance(summary, Mapping) else type(summary).__name__
            raise ValueError(
                f"{summary_path}: expected a dict of scenario file name -> metadata, got {got}"
            )
    else:
        names = sorted(e.name for e in os.scandir(folder) if e.is_file())
        summary = {name: {} for name in names if is_scenario_file(name)}
        if not summary:
            raise FileNotFoundError(
                f"{folder}: no {SUMMARY_FILE} and no scenario files (sd_*.pkl): not a "
                "ScenarioNet dataset folder (python -m scenarionet.convert_<source> -d "
                "FOLDER writes one)"
            )
    for name, metadata in summary.items():
        if not _plain_file_name(name):
            raise ValueError(
                f"{summary_path}: entry {brief(name)} is not a scenario file name (*.pkl)"
            )
        if not isinstance(metadata, Mapping):
            raise ValueError(
                f"{summary_path}: the metadata of {name} must be a dict, "
                f"got {type(metadata).__name__}"
            )
        if len(metadata) > MAX_METADATA_KEYS:
            raise ValueError(
                f"{summary_path}: the metadata of {name} holds {len(metadata)} keys, over the "
                f"limit MAX_METADATA_KEYS = {MAX_METADATA_KEYS}"
            )
    if not mapping_path.is_file():
        return dict(summary), dict.fromkeys(summary, "")
    mapping = load_data_pickle(mapping_path)
    if not isinstance(mapping, Mapping):
        raise ValueError(
            f"{mapping_path}: expected a dict of scenario file name -> relative folder, "
            f"got {type(mapping).__name__}"
        )
    for name in summary:
        if name not in mapping:
            raise ValueError(f"{mapping_path}: no entry for {name}, listed in {summary_path}")
        where = mapping[name]
        if not isinstance(where, str) or "\x00" in where or os.path.isabs(where):
            raise ValueError(
                f"{mapping_path}: the folder of {name} must be a relative path, got {brief(where)}"
            )
    return dict(summary), {name: mapping[name] for name in summary}


def _plain_file_name(name: object) -> bool:
    return (
        isinstance(name, str)
        and len(name) <= MAX_FILE_NAME
        and name.endswith(".pkl")
        and name not in INDEX_FILES
        and "\x00" not in name
        and Path(name).name == name
        and "\\" not in name
    )


def _names(files: tuple[str, ...], summaries: tuple[Mapping, ...], where: Path) -> tuple[str, ...]:
    """``scenarionet/<id>`` per file; the file stem where the id is absent or repeated;
    ValueError naming ``where`` (the summary) and the entry for an id too long."""
    ids = []
    for file, metadata in zip(files, summaries, strict=True):
        found = metadata.get("scenario_id", metadata.get("id"))
        if isinstance(found, (str, int)):
            found = entry_id(found, f"{where}: entry {file[:MAX_QUOTE]}: the scenario id")
        ids.append(found if isinstance(found, str) and found else None)
    counts: dict[str | None, int] = {}
    for scene_id in ids:
        counts[scene_id] = counts.get(scene_id, 0) + 1
    return tuple(
        f"scenarionet/{scene_id}" if scene_id is not None and counts[scene_id] == 1 else
        f"scenarionet/{file[:-4]}"
        for file, scene_id in zip(files, ids, strict=True)
    )  # fmt: skip
