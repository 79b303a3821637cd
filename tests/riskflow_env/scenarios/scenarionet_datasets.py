"""ScenarioNet dataset folders in the exact form ScenarioNet writes them (no data files).

ScenarioNet's converters (``scenarionet/converter/utils.py``, ``write_to_directory``)
split the scenes over W workers; worker i writes its scenario files
``sd_<dataset>_<version>_<scenario id>.pkl`` into ``<folder>/<folder name>_<i>``, with
its own ``dataset_summary.pkl`` (file name -> the scenario's ``metadata``) and
``dataset_mapping.pkl`` (file name -> ``""``, same folder). ``merge_database``
(``scenarionet/builder/utils.py``) then writes ``<folder>/dataset_summary.pkl`` (every
worker's summary, in worker order) and ``<folder>/dataset_mapping.pkl`` (file name -> the
worker folder relative to ``<folder>``). Summaries are stored as
``common_utils.dict_recursive_remove_array_and_set`` leaves them: inside dicts, numpy
arrays become lists and sets become tuples; other containers are kept (the
``defaultdict`` of ``number_summary`` included). Everything is written with
``pickle.dump`` at its default protocol.
"""

from __future__ import annotations

import copy
import pickle
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from riskflow_env.scenarios.safe_pickle import load_data_pickle
from tests.riskflow_env.scenarios.scenarionet_sources import description

SUMMARY, MAPPING = "dataset_summary.pkl", "dataset_mapping.pkl"


def summary_form(value: Any) -> Any:
    """``value`` as ScenarioNet stores it in a summary (arrays -> lists, sets -> tuples,
    recursing into dicts only; dicts are changed in place, as ScenarioNet does)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, set):
        return tuple(value)
    if isinstance(value, dict):
        for key in value:
            value[key] = summary_form(value[key])
    return value


def toy_descriptions(count: int, source: str = "nuscenes") -> list[dict]:
    """``count`` scenes of ``source`` (scenarionet_sources), ids ``<source>-toy-<k>``; scene
    k's vehicles start k * 2 m further along (so every file differs)."""
    scenes = []
    for k in range(count):
        scene = description(source)
        scene_id = f"{source}-toy-{k}"
        scene["id"] = scene["metadata"]["id"] = scene["metadata"]["scenario_id"] = scene_id
        for track in scene["tracks"].values():
            track["state"]["position"][:, 0] += 2.0 * k
        scenes.append(scene)
    return scenes


def _dump(path: Path, value: Any) -> None:
    with path.open("wb") as file:
        pickle.dump(value, file)


def write_dataset(
    folder: Path,
    scenes: Sequence[dict | Path],
    dataset: str = "nuscenes",
    version: str = "v1.0-mini",
    workers: int = 2,
) -> list[str]:
    """Write ``scenes`` (descriptions, or scenario files to copy) as ScenarioNet's
    ``convert_<dataset>`` with ``workers`` workers does; returns the file names in the
    summary's order."""
    folder.mkdir(parents=True, exist_ok=True)
    per_worker = len(scenes) // workers if len(scenes) >= workers else len(scenes)
    count = workers if len(scenes) >= workers else 1
    summary: dict[str, Any] = {}
    mapping: dict[str, str] = {}
    for worker in range(count):
        end = len(scenes) if worker == count - 1 else (worker + 1) * per_worker
        sub = folder / f"{folder.name}_{worker}"
        sub.mkdir()
        own: dict[str, Any] = {}
        for scene in scenes[worker * per_worker : end]:
            data = load_data_pickle(scene) if isinstance(scene, Path) else scene
            name = f"sd_{dataset}_{version}_{data['id']}.pkl"
            if isinstance(scene, Path):
                shutil.copy(scene, sub / name)
            else:
                _dump(sub / name, data)
            own[name] = copy.deepcopy(data["metadata"])
        _dump(sub / SUMMARY, summary_form(copy.deepcopy(own)))
        _dump(sub / MAPPING, dict.fromkeys(own, ""))
        summary.update(own)
        mapping.update(dict.fromkeys(own, sub.name))
    _dump(folder / SUMMARY, summary_form(summary))
    _dump(folder / MAPPING, mapping)
    return list(summary)
