"""Training batches: the train / validation split, cached windows, seeded batch order.

Windows come from ``WindowDataset`` (``docs/how-to/windows.md``), cached as ``.npz`` under the
scene folder's ``cache/`` (the user cache for the shipped bank: ``data_cache``). The
batch order of an epoch is a pure function of (seed, epoch), so a resumed run sees the
same batches as an uninterrupted one; batches are drawn from pools sorted by agent count,
which halves the padding (and the step time: 20.8 against 10.4 windows/s on the
validation bank, 19 against 30 agent slots). With ``--data-weights`` (:class:`FolderShares`)
each folder gives its stated share of every epoch's windows instead of its share of the
windows.

Recorded scenes (a ScenarioNet folder) are read with ``smooth=True``
(:func:`training_scenes`): nuScenes tracks are 2 Hz keyframes that ScenarioNet interpolates
linearly to 10 Hz, so their accelerations jump every 0.5 s; the Savitzky-Golay fit
(``riskflow_env.scenarios.smoothing``) gives tracks that the unicycle reproduces. On the
four nuScenes samples, a window's own (bounded, inverse-dynamics) actions rolled out from
its current states miss its future by 0.09 m on average and 0.43 m at the 95th percentile
(raw logs: 0.32 and 1.40 m), and their |jerk| p95 is 3.5 m/s^3 (raw: 27).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from policies.learned.data import WindowDataset
from policies.learned.data_cache import derived_dir
from policies.learned.recovery import RecoveryConfig
from policies.learned.window_types import WindowBatch, collate_windows
from policies.learned.windows import WindowConfig
from riskflow_env.scenarios.folders import scene_files
from riskflow_env.scenarios.io import load_scenario
from riskflow_env.scenarios.scenario import Scenario
from riskflow_env.scenarios.scenarionet_dataset import ScenarioNetDataset


def load_splits(
    data: Path | Sequence[Path],
    val_data: Path | None,
    val_fraction: float,
    stride: int,
    recovery: RecoveryConfig | None = None,
    window: WindowConfig | None = None,
) -> tuple[WindowDataset, WindowDataset]:
    """Training and validation windows, cached under ``<folder>/cache/``.

    A folder inside the installed packages or not writable keeps its cache in the user
    cache instead (:func:`policies.learned.data_cache.derived_dir`).

    Args:
        data: scene folder of the training split: ``.npz`` scenes (``riskflow-data
            generate``) or a ScenarioNet dataset (read one scene at a time while the
            windows are cut; ``riskflow_env.scenarios.folders.scene_files``); or several
            such folders, whose scenes are used together (one folder's after the other's;
            their windows are cached under the first folder, and ``val_data`` is needed).
        val_data: scene folder of the validation split; None holds out
            ``round(val_fraction * scenes)`` of ``data``'s scenes (the same ones for
            any training seed).
        val_fraction: see ``val_data``.
        stride: steps between windows of a scene (``WindowDataset``).
        recovery: recovery windows added to the training split only
            (:mod:`policies.learned.recovery`); their cache has its own file.
        window: how windows are cut (None: ``WindowConfig()``; a model's own:
            :func:`~policies.learned.adversary_config.default_window_config`).
    """
    folders = [Path(data)] if isinstance(data, (str, Path)) else [Path(f) for f in data]
    if not folders:
        raise ValueError("no training scene folder given")
    if len(folders) > 1 and val_data is None:
        raise ValueError(
            f"{len(folders)} training scene folders need a validation folder (--val-data): "
            "the held-out share (--val-fraction) is taken from one folder only"
        )
    data = folders[0]
    name = f"windows-stride{stride}"
    train_name = name
    if recovery is not None and recovery.copies:
        settings = json.dumps(recovery.settings(), sort_keys=True).encode()
        train_name += f"-recovery-{hashlib.sha256(settings).hexdigest()[:12]}"
    if len(folders) > 1:  # the set of folders, in order, names the cache file
        together = "\n".join(str(f.resolve()) for f in folders).encode()
        train_name += f"-with-{hashlib.sha256(together).hexdigest()[:12]}"
    caches = {}
    for folder in (data, val_data):
        if folder is not None:
            caches[folder] = derived_dir(folder) / "cache"
            caches[folder].mkdir(parents=True, exist_ok=True)
    if val_data is not None:
        sources = [_source(folder) for folder in folders]
        # one folder is passed alone: its cache fingerprint stays that of earlier versions
        train = WindowDataset(
            sources if len(sources) > 1 else sources[0], window, stride,
            caches[data] / f"{train_name}.npz", recovery,
        )  # fmt: skip
        val = WindowDataset(_source(val_data), window, stride, caches[val_data] / f"{name}.npz")
        return train, val
    scenes = training_scenes(data)
    count = round(val_fraction * len(scenes))
    if not 0 < count < len(scenes):
        raise ValueError(
            f"--val-fraction {val_fraction} of the {len(scenes)} scene(s) of {data} puts "
            f"{count} in validation: give more scenes, another --val-fraction or --val-data"
        )
    order = np.random.default_rng(0).permutation(len(scenes))
    datasets = []
    for role, part in (("train", order[count:]), ("val", order[:count])):
        picked = sorted(int(i) for i in part)
        if isinstance(scenes, ScenarioNetDataset):  # read one at a time by WindowDataset
            source: ScenarioNetDataset | list[Scenario] = scenes.subset(picked)
        else:
            source = [load_scenario(scenes[i]) for i in picked]
        prefix, extra = (train_name, recovery) if role == "train" else (name, None)
        cache = caches[data] / f"{prefix}-val{val_fraction:g}-{role}.npz"
        datasets.append(WindowDataset(source, window, stride, cache, extra))
    return datasets[0], datasets[1]


def training_scenes(folder: Path) -> list[Path] | ScenarioNetDataset:
    """The scenes of ``folder`` (``scene_files``); a ScenarioNet dataset is opened with
    ``smooth=True``, its tracks replaced by their kinematic reference filtering (module
    docstring)."""
    scenes = scene_files(folder)
    if isinstance(scenes, ScenarioNetDataset):
        return ScenarioNetDataset(folder, smooth=True)
    return scenes


def _source(folder: Path) -> Path | ScenarioNetDataset:
    """What ``WindowDataset`` reads for ``folder``: the folder of ``.npz`` scenes itself,
    or its ScenarioNet dataset (:func:`training_scenes`)."""
    scenes = training_scenes(folder)
    return scenes if isinstance(scenes, ScenarioNetDataset) else folder


@dataclass(frozen=True)
class FolderShares:
    """Each training folder's share of every epoch's windows (``--data-weights``).

    Attributes:
        folders: ``(W,)`` int, the ``--data`` folder (position) of each window.
        weights: one per folder, > 0: folder ``k`` gives ``weights[k] / sum(weights)`` of
            the windows (largest-remainder rounding); a small folder's windows repeat
            within an epoch, a large one's are drawn without repeats.
    """

    folders: np.ndarray
    weights: tuple[float, ...]

    @classmethod
    def of(
        cls, dataset: WindowDataset, data: Sequence[Path], weights: Sequence[float]
    ) -> FolderShares:
        """The shares of ``dataset``, cut from the folders ``data`` in that order."""
        ends = np.cumsum([len(scene_files(folder)) for folder in data])
        folders = np.searchsorted(ends, dataset.index[:, 0], side="right")
        empty = [str(data[k]) for k in range(len(data)) if not np.any(folders == k)]
        if empty:
            raise ValueError(f"--data-weights: no training window in {', '.join(empty)}")
        return cls(folders, tuple(float(w) for w in weights))

    def draw(self, count: int, gen: torch.Generator) -> np.ndarray:
        """``(count,)`` window indices in a seeded order, each folder its share."""
        exact = count * np.asarray(self.weights) / sum(self.weights)
        quota = np.floor(exact).astype(np.int64)
        extra = np.argsort(-(exact - quota), kind="stable")[: count - quota.sum()]
        quota[extra] += 1
        picks = []
        for folder, size in enumerate(quota):
            members = np.flatnonzero(self.folders == folder)
            rounds = -(-int(size) // len(members))
            drawn = [
                members[torch.randperm(len(members), generator=gen).numpy()] for _ in range(rounds)
            ]
            picks.append(np.concatenate(drawn)[:size] if drawn else members[:0])
        order = np.concatenate(picks)
        return order[torch.randperm(count, generator=gen).numpy()]


def batch_order(
    agents: np.ndarray,
    batch_size: int,
    bucket: int,
    seed: int,
    epoch: int,
    shares: FolderShares | None = None,
) -> np.ndarray:
    """``(batches, batch_size)`` window indices of ``epoch``, a pure function of the arguments.

    A seeded permutation (the incomplete last batch dropped; with ``shares``, as many
    windows drawn by folder, :meth:`FolderShares.draw`), cut into pools of ``bucket``
    batches; each pool is sorted by agent count (so a batch pads little) and cut into
    batches, and the batches are shuffled.
    """
    gen = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
    count = len(agents) // batch_size * batch_size
    if shares is None:
        order = torch.randperm(len(agents), generator=gen)[:count].numpy()
    else:
        order = shares.draw(count, gen)
    pool = batch_size * bucket
    for start in range(0, count, pool):
        chunk = order[start : start + pool]
        order[start : start + pool] = chunk[np.argsort(agents[chunk], kind="stable")]
    batches = order.reshape(-1, batch_size)
    return batches[torch.randperm(len(batches), generator=gen).numpy()]


def collated(dataset: WindowDataset, indices: Sequence[int], device: str) -> WindowBatch:
    """``collate_windows`` of ``dataset[indices]``, on ``device``."""
    return collate_windows([dataset[int(i)] for i in indices]).to(device)
