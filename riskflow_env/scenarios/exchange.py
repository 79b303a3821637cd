"""Scenarios in and out of other tools' formats (docs/how-to/exchange.md).

* :func:`export_scenario` writes a :class:`~riskflow_env.scenarios.Scenario` as a
  ScenarioNet / MetaDrive pickle (:mod:`~riskflow_env.scenarios.scenarionet_export`) or
  as ASAM OpenSCENARIO with an OpenDRIVE road
  (:mod:`~riskflow_env.scenarios.openscenario_export`) or as CommonRoad XML
  (:mod:`~riskflow_env.scenarios.commonroad_export`).
  A rollout is exported as the scenario of its executed states
  (``EpisodeRecord.to_scenario()``: every vehicle's history, then what it did).
* :func:`read_scene` reads one scene file of any kind the package reads (``riskflow-data
  export`` takes them); CommonRoad scenarios are read by
  :mod:`~riskflow_env.scenarios.commonroad_import`.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Sequence
from pathlib import Path

from riskflow_env.folder_lock import make_output_folder
from riskflow_env.scenarios.scenario import Scenario

FORMATS = ("scenarionet", "openscenario", "commonroad")
SUFFIXES = {"scenarionet": ".pkl", "openscenario": ".xosc", "commonroad": ".xml"}


def export_scenario(scenario: Scenario, path: str | os.PathLike, format: str) -> list[Path]:
    """Write ``scenario`` to ``path`` in ``format`` (one of :data:`FORMATS`).

    Args:
        scenario: the scene, or a rollout's executed scenario.
        path: the file to write; the format's suffix (:data:`SUFFIXES`) replaces a
            scene file's suffix (``.npz``, ``.pkl``, ``.xml``, ``.xosc``) and is added to
            any other name (``scene-0061.v1`` -> ``scene-0061.v1.pkl``).
        format: ``"scenarionet"`` (:mod:`~riskflow_env.scenarios.scenarionet_export`) or
            ``"openscenario"`` (``.xosc``, with an OpenDRIVE ``.xodr`` beside it for a
            highway-env map: :mod:`~riskflow_env.scenarios.openscenario_export`; the
            ``[interop]`` extra) or ``"commonroad"`` (``.xml``:
            :mod:`~riskflow_env.scenarios.commonroad_export`, the ``[interop]`` extra).

    Returns:
        The files written.
    """
    require_format(format)
    if not isinstance(scenario, Scenario):
        raise TypeError(f"scenario must be a Scenario, got {type(scenario).__name__}")
    path = output_path(path, format)
    if format == "commonroad":
        from riskflow_env.scenarios.commonroad_export import save_commonroad

        return [save_commonroad(scenario, path)]
    if format == "openscenario":
        from riskflow_env.scenarios.openscenario_export import save_openscenario

        return save_openscenario(scenario, path)
    from riskflow_env.scenarios.scenarionet_export import save_scenarionet

    return [save_scenarionet(scenario, path)]


SCENE_SUFFIXES = (".npz", ".pkl", ".xml", ".xosc")


def output_path(path: str | os.PathLike, format: str) -> Path:
    """``path`` with ``format``'s suffix (:func:`export_scenario`'s rule)."""
    path = Path(path)
    if path.suffix in SCENE_SUFFIXES:
        return path.with_suffix(SUFFIXES[format])
    return path.with_name(path.name + SUFFIXES[format])


def require_format(format: str) -> None:
    """ValueError unless ``format`` is one of :data:`FORMATS`; ImportError saying how to
    install what it needs when a library of the ``[interop]`` extra is missing."""
    if format not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {format!r}")
    if format == "commonroad":
        from riskflow_env.scenarios.commonroad_import import commonroad_io

        commonroad_io()
    elif format == "openscenario":
        _require("scenariogeneration", "OpenSCENARIO / OpenDRIVE files")


def _require(module: str, what: str) -> None:
    """ImportError saying how to install ``module`` when it does not import."""
    try:
        importlib.import_module(module)
    except ImportError as err:
        raise ImportError(
            f"{what} need {module}: pip install 'riskflow-env[interop]' ({err})"
        ) from None


def read_scene(path: str | os.PathLike) -> Scenario:
    """The scene of ``path``: a RiskFlow ``.npz`` scene (or replay) file, a ScenarioNet
    ``.pkl`` or a CommonRoad ``.xml``.

    Raises:
        FileNotFoundError, IsADirectoryError: no such file, or a folder.
        ValueError: naming the file, for another suffix or a malformed file, or a
            CommonRoad file without commonroad-io (the ``[interop]`` extra).
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{str(path)!r} is a folder: give its scene files")
    if not path.is_file():
        raise FileNotFoundError(f"no such scene file {str(path)!r}")
    if path.suffix == ".npz":
        from riskflow_env.scenarios.io import load_scenario

        return load_scenario(path)
    if path.suffix == ".pkl":
        from riskflow_env.scenarios.scenarionet import load_scenarionet

        return load_scenarionet(path)
    if path.suffix == ".xml":
        from riskflow_env.scenarios.commonroad_import import load_commonroad

        try:
            return load_commonroad(path)
        except ImportError as err:  # a user error here: say which file needs the extra
            raise ValueError(f"{path} is a CommonRoad scenario: {err}") from None
    raise ValueError(f"{path}: expected a .npz scene file, a ScenarioNet .pkl or a CommonRoad .xml")


def export_files(
    files: Sequence[str | os.PathLike], formats: Sequence[str], out: str | os.PathLike
) -> list[Path]:
    """Write every scene file of ``files`` (:func:`read_scene`) in every format of
    ``formats`` as ``out/<file stem>.<suffix>`` (``riskflow-data export``); returns the
    files written.

    Raises:
        ValueError: two inputs would write the same file, or an output would overwrite
            an input (both named).
    """
    inputs = {Path(path).resolve(): Path(path) for path in files}
    targets: dict[Path, Path] = {}
    for path in files:
        for fmt in formats:
            target = output_path(Path(out) / Path(path).name, fmt).resolve()
            if target in inputs:
                raise ValueError(f"{path}: its {fmt} export would overwrite {inputs[target]}")
            if targets.setdefault(target, Path(path)) != Path(path):
                raise ValueError(f"{targets[target]} and {path} would both be exported as {target}")
    scenarios = [read_scene(path) for path in files]  # every input read before any write
    make_output_folder(out, "--out")
    written = []
    for path, scenario in zip(files, scenarios, strict=True):
        for fmt in formats:
            written += export_scenario(scenario, Path(out) / Path(path).name, fmt)
    return written


__all__ = [
    "FORMATS",
    "SUFFIXES",
    "export_files",
    "export_scenario",
    "read_scene",
    "require_format",
]
