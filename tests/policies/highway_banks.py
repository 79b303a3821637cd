"""Scene folders as ``riskflow-data generate`` writes them, for the training tests."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from riskflow_env.scenarios import HighwayTrafficSource
from riskflow_env.scenarios.io import save_scenario


def write_banks(folders: Sequence[Path], seeds: Sequence[Sequence[int]]) -> tuple[Path, ...]:
    """Folder ``i`` gets one highway scene per seed of ``seeds[i]`` (``SSSSS-highway.npz``,
    maps in ``maps/``); returns the folders."""
    for folder, folder_seeds in zip(folders, seeds, strict=True):
        folder.mkdir(parents=True)
        for seed in folder_seeds:
            scene = HighwayTrafficSource().sample(np.random.default_rng(seed))
            save_scenario(scene, folder / f"{seed:05d}-highway.npz", map_dir=folder / "maps")
    return tuple(folders)
