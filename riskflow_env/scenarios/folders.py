"""Open a folder of scenes, whichever kind it is.

* a ScenarioNet dataset folder (``dataset_summary.pkl`` + ``dataset_mapping.pkl``, or
  ScenarioNet scenario files ``sd_*.pkl`` alone): a lazy
  :class:`~riskflow_env.scenarios.scenarionet_dataset.ScenarioNetDataset`, which reads a
  scene when it is drawn;
* a folder of RiskFlow ``.npz`` scene files (``riskflow-data generate``): a
  :class:`~riskflow_env.scenarios.sources.ScenarioBank` with every scene loaded;
* a folder of CommonRoad ``.xml`` scenarios and no ``.npz``: a ScenarioBank of them
  (:func:`~riskflow_env.scenarios.commonroad_import.load_commonroad`, ``[interop]`` extra).

``parallel_env(scenarios=folder)`` and ``riskflow-eval --data`` open their folder with
:func:`open_scenes`; ``riskflow-train --data`` with :func:`scene_files` (it reads the
scenes one at a time when it cuts their training windows).
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Mapping
from pathlib import Path

from riskflow_env.config import is_integer
from riskflow_env.scenarios.commonroad_import import is_commonroad_file, load_commonroad
from riskflow_env.scenarios.io import ONE_FILE, load_bank, require_scenarios
from riskflow_env.scenarios.safe_pickle import load_data_pickle
from riskflow_env.scenarios.scenarionet_dataset import ScenarioNetDataset, is_scenarionet_folder
from riskflow_env.scenarios.sources import ScenarioBank


def open_scenes(folder: str | os.PathLike) -> ScenarioBank | ScenarioNetDataset:
    """The scenes of ``folder`` (module docstring); both kinds have ``len``, indexing,
    ``names`` and ``sample(rng)``.

    Raises:
        FileNotFoundError, NotADirectoryError: no such folder, a file, or no scenes in it.
        ValueError: naming the file, for a malformed index or scene file; naming the folder,
            for CommonRoad scenarios without commonroad-io.
    """
    if Path(folder).is_file():  # one scene file given where a folder of them goes
        raise NotADirectoryError(f"{folder} is a file; expected {FOLDER_KINDS}; {ONE_FILE}")
    if is_scenarionet_folder(folder):
        return ScenarioNetDataset(folder)
    commonroad = commonroad_files(folder)
    if commonroad:
        try:
            return ScenarioBank([load_commonroad(path) for path in commonroad])
        except ImportError as err:  # a user error here: say which folder needs the extra
            raise ValueError(f"{folder} holds CommonRoad scenarios: {err}") from None
    if Path(folder).is_dir() and not any(Path(folder).glob("*.npz")):
        raise FileNotFoundError(f"no scenes in {folder}: expected {FOLDER_KINDS}")
    return load_bank(folder)


FOLDER_KINDS = (
    "a folder of .npz scenes (riskflow-data generate), a ScenarioNet dataset folder (.pkl "
    "scenario files, with or without its index files) or CommonRoad .xml scenarios"
)


def commonroad_files(folder: str | os.PathLike) -> list[Path]:
    """The CommonRoad ``.xml`` files of ``folder`` when it holds no ``.npz`` scene, else []."""
    folder = Path(folder)
    if not folder.is_dir() or any(folder.glob("*.npz")):
        return []
    return [path for path in sorted(folder.glob("*.xml")) if is_commonroad_file(path)]


def scene_files(folder: str | os.PathLike) -> list[Path] | ScenarioNetDataset:
    """The scenes of ``folder`` without loading any: the ``.npz`` scene files of a RiskFlow
    folder, or a ScenarioNet dataset (whose every scenario file exists).

    Raises:
        FileNotFoundError, NotADirectoryError: no such folder, a file, no scenes in it, or
            a scenario file that the dataset's summary lists is missing (named).
        ValueError: naming the file, for a malformed ScenarioNet index file.
    """
    if Path(folder).is_file():
        raise NotADirectoryError(
            f"{folder} is a file; expected a folder of .npz scenes (riskflow-data generate) or "
            f"a ScenarioNet dataset folder; {ONE_FILE}"
        )
    if not is_scenarionet_folder(folder):
        return require_scenarios(folder)
    dataset = ScenarioNetDataset(folder)
    missing = dataset.missing_files()
    if missing:
        raise FileNotFoundError(
            f"{folder}: {len(missing)} scenario file(s) listed in its summary are missing, "
            f"e.g. {missing[0]}"
        )
    return dataset


def scenarionet_counts(folder: str | os.PathLike) -> tuple[Counter, Counter, int, int]:
    """``(scenes, objects, missing, size)`` of a ScenarioNet dataset folder: scenes and
    objects (every kind of traffic participant) per source dataset, from the summary's
    metadata, or from each scenario file's own where the folder has no summary (every file
    is read then; no map is converted); the files listed but missing; the bytes of those
    present. ValueError naming a file that is not a readable data pickle; FileNotFoundError
    when no listed file is present."""
    dataset = ScenarioNetDataset(folder, map_cache=False)
    scenes: Counter[str] = Counter()
    objects: Counter[str] = Counter()
    missing, size = 0, 0
    for index in range(len(dataset)):
        path = dataset.path(index)
        if not path.is_file():
            missing += 1
            continue
        size += path.stat().st_size
        metadata = dataset.summaries[index] or _file_metadata(path)
        source = metadata.get("dataset")
        source = source if isinstance(source, str) and source else "unknown"
        numbers = metadata.get("number_summary")
        count = numbers.get("num_objects") if isinstance(numbers, Mapping) else None
        scenes[source] += 1
        objects[source] += int(count) if is_integer(count) else 0
    if not scenes:
        raise FileNotFoundError(
            f"{folder}: none of the {missing} scenario files its summary lists is present"
        )
    return scenes, objects, missing, size


def _file_metadata(path: Path) -> Mapping:
    """The ``metadata`` of a ScenarioNet scenario file ({} where it has none)."""
    description = load_data_pickle(path)
    metadata = description.get("metadata") if isinstance(description, Mapping) else None
    return metadata if isinstance(metadata, Mapping) else {}
