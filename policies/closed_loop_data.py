"""``riskflow-closed-loop``: training scenes from the generator's own closed-loop rollouts.

::

    riskflow-closed-loop --data data/train data/train_stops --out data/closed_loop
    riskflow-train --data data/train data/train_stops data/closed_loop --val-data data/val \\
        --init policies/checkpoints/riskflow_default.pt --steps 2000 --lr 5e-4 ...

The generator (``--checkpoint``, default the shipped one) drives every scene of ``--data``
from its current step, re-planning every ``--interval`` steps and executing, per agent,
the one of ``--candidates`` plans closest to the log (CAT-K); every ``--every`` cycles the
scene is cut into a training scene whose history is the closed-loop one and whose future
returns to the log (:mod:`policies.learned.closed_loop`). The scenes are written as a
scene folder (``maps/`` holds each map once; ``riskflow-closed-loop.json`` the settings
and counts), one file per scene, each written whole (a run stopped midway leaves only
complete files); ``riskflow-train --data`` reads it beside the recorded folders.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm import tqdm

from policies.dataclass_cli import parse_dataclass
from policies.evaluation.options import check_device
from policies.learned.adversary_config import default_window_config
from policies.learned.checkpoint import load_generator
from policies.learned.closed_loop import ClosedLoopConfig, closed_loop_scenes
from riskflow_env.scenarios.io import list_scenarios, load_scenario, save_scenario

MANIFEST = "riskflow-closed-loop.json"


@dataclass(frozen=True, kw_only=True)
class ClosedLoopOptions(ClosedLoopConfig):
    """Options of ``riskflow-closed-loop``: the scenes, then the drive and its targets."""

    data: tuple[Path, ...]
    """recorded scene folders (written by `riskflow-data generate`) whose scenes are driven"""
    out: Path
    """new (or empty) folder for the closed-loop training scenes"""
    checkpoint: Path | None = None
    """generator that drives (default: the shipped policies/checkpoints/riskflow_default.pt)"""
    scenes: int = 0
    """scenes of each --data folder used, the first ones (0: all)"""
    device: str = "cpu"
    """'cpu' or 'cuda' (or 'cuda:N'): where the generator runs"""
    threads: int = 1
    """torch CPU threads (0: torch's default)"""

    def __post_init__(self) -> None:
        object.__setattr__(self, "data", tuple(Path(folder) for folder in self.data))
        if not self.data:
            raise ValueError("--data needs at least one scene folder")
        if self.scenes < 0 or self.threads < 0:
            raise ValueError(
                f"--scenes and --threads must be >= 0, got {self.scenes}, {self.threads}"
            )
        try:
            super().__post_init__()
        except ValueError as error:  # name the flag, not the config field
            field = str(error).split(" ")[0].removeprefix("ClosedLoopConfig.")
            raise ValueError(f"--{field.replace('_', '-')}: {error}") from None

    def config(self) -> ClosedLoopConfig:
        """The drive and return objective of these options."""
        names = [field.name for field in dataclasses.fields(ClosedLoopConfig)]
        return ClosedLoopConfig(**{name: getattr(self, name) for name in names})


def _check(options: ClosedLoopOptions) -> list[list[Path]]:
    """Scene paths of each folder; bad folders, devices and outputs raise ValueError."""
    if options.out.exists() and (not options.out.is_dir() or list_scenarios(options.out)):
        raise ValueError(f"--out {options.out} must be a new or empty folder (it holds scenes)")
    paths = []
    for folder in options.data:
        if not folder.is_dir():
            raise ValueError(f"--data {folder} is not a folder")
        found = list_scenarios(folder)
        if not found:
            raise ValueError(f"--data {folder} holds no scene files (riskflow-data generate)")
        paths.append(found[: options.scenes] if options.scenes else found)
    check_device(options.device)
    return paths


def write(options: ClosedLoopOptions) -> dict:
    """Drive every scene and write the training scenes; returns the manifest."""
    paths = _check(options)
    if options.threads:
        torch.set_num_threads(options.threads)
    model, normalizer, _ = load_generator(options.checkpoint, options.device)
    window_config = default_window_config(model.config)
    config = options.config()
    manifest = {
        "command": "riskflow-closed-loop",
        "data": [str(folder) for folder in options.data],
        "checkpoint": str(options.checkpoint or "policies/checkpoints/riskflow_default.pt"),
        "checkpoint_sha256": hashlib.sha256(Path(options.checkpoint).read_bytes()).hexdigest()
        if options.checkpoint
        else None,
        "settings": dataclasses.asdict(config),
        "recorded_scenes": 0,
        "scenes": 0,
    }
    options.out.mkdir(parents=True, exist_ok=True)
    started, position = time.perf_counter(), 0
    total = sum(len(group) for group in paths)
    with tqdm(total=total, desc="closed-loop scenes", unit="scene") as progress:
        for folder, group in enumerate(paths):
            for path in group:
                scenes = closed_loop_scenes(
                    load_scenario(path), model, normalizer, window_config, config, position
                )
                for scene in scenes:
                    name = f"{folder:02d}-{Path(path).stem}-{scene.name.rsplit('-', 1)[1]}.npz"
                    save_scenario(scene, options.out / name, map_dir=options.out / "maps")
                manifest["recorded_scenes"] += 1
                manifest["scenes"] += len(scenes)
                position += 1
                progress.update()
    manifest["seconds"] = round(time.perf_counter() - started, 1)
    (options.out / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``riskflow-closed-loop`` console script."""
    options = parse_dataclass(
        ClosedLoopOptions, argv, "riskflow-closed-loop", __doc__.split("\n")[0]
    )
    try:
        manifest = write(options)
    except ValueError as error:
        print(f"riskflow-closed-loop: error: {error}", file=sys.stderr)
        return 2
    print(
        f"wrote {manifest['scenes']} closed-loop scenes of {manifest['recorded_scenes']} recorded "
        f"ones to {options.out} in {manifest['seconds']} s"
    )
    return 0


__all__ = ["MANIFEST", "ClosedLoopOptions", "main", "write"]

if __name__ == "__main__":
    sys.exit(main())
