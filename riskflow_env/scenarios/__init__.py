"""Scenarios and where they come from.

* :class:`Scenario` — one scene (map, sizes, tracks, ego); sources draw them.
* Synthetic: :class:`HighwayTrafficSource` (lane-following placement, any family).
* Naturalistic: :func:`generate_scenario` (highway-env IDM/MOBIL recordings cut into
  windows, :mod:`~riskflow_env.scenarios.naturalistic`); ``riskflow-data`` makes banks.
* Files: :func:`save_scenario` / :func:`load_scenario` (versioned ``.npz``),
  :func:`load_bank` (a folder), :func:`shipped_bank` (the scenes in the package; the
  ``"eval"`` split is the env's default source).
* Recorded data: :mod:`~riskflow_env.scenarios.scenarionet` (one ScenarioNet file),
  :mod:`~riskflow_env.scenarios.scenarionet_dataset` (a ScenarioNet dataset folder as a
  lazy source), :mod:`~riskflow_env.scenarios.map_cache` (converted maps on disk),
  :mod:`~riskflow_env.scenarios.folders` (open a folder of either kind).
"""

from riskflow_env.scenarios._npz import ScenarioFormatError
from riskflow_env.scenarios.io import (
    SPLITS,
    list_scenarios,
    load_bank,
    load_map,
    load_scenario,
    save_scenario,
    shipped_bank,
)
from riskflow_env.scenarios.naturalistic import (
    SceneConfig,
    cut_scenario,
    cut_scenarios,
    generate_scenario,
)
from riskflow_env.scenarios.recording import DriverConfig, Recording, record_traffic
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.scenarios.sources import ScenarioBank, ScenarioSource, as_source
from riskflow_env.scenarios.traffic import HighwayTrafficSource, TrafficConfig, place_traffic

__all__ = [
    "DriverConfig",
    "HighwayTrafficSource",
    "Recording",
    "Scenario",
    "ScenarioBank",
    "ScenarioFormatError",
    "ScenarioSource",
    "SceneConfig",
    "SPLITS",
    "TrafficConfig",
    "as_source",
    "cut_scenario",
    "cut_scenarios",
    "generate_scenario",
    "list_scenarios",
    "load_bank",
    "load_map",
    "load_scenario",
    "place_traffic",
    "record_traffic",
    "save_scenario",
    "shipped_bank",
]
