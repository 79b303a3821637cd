"""Open a folder of scenes, whichever kind it is.

* a ScenarioNet dataset folder (``dataset_summary.pkl`` + ``dataset_mapping.pkl``, or
  ScenarioNet scenario files ``sd_*.pkl`` alone): a lazy
  :class:`~riskflow_env.scenarios.scenarionet_dataset.ScenarioNetDataset`, which reads a
  scene when it is drawn;
* a folder of RiskFlow ``.npz`` scene files (``riskflow-data generate``): a
  :class:`~riskflow_env.scenarios.sources.ScenarioBank` with every scene loaded.

``parallel_env(scenarios=folder)``, ``riskflow-eval --data`` and ``riskflow-train --data``
open their folder with :func:`open_scenes`.
"""

from __future__ import annotations

import os

from riskflow_env.scenarios.io import load_bank
from riskflow_env.scenarios.scenarionet_dataset import ScenarioNetDataset, is_scenarionet_folder
from riskflow_env.scenarios.sources import ScenarioBank


def open_scenes(folder: str | os.PathLike) -> ScenarioBank | ScenarioNetDataset:
    """The scenes of ``folder`` (module docstring); both kinds have ``len``, indexing,
    ``names`` and ``sample(rng)``.

    Raises:
        FileNotFoundError, NotADirectoryError: no such folder, a file, or no scenes in it.
        ValueError: naming the file, for a malformed index or scene file.
    """
    if is_scenarionet_folder(folder):
        return ScenarioNetDataset(folder)
    return load_bank(folder)
