"""``riskflow-data``: generate naturalistic scenario banks and describe them.

::

    riskflow-data generate --families highway merge roundabout --scenes 300 \\
        --out data/train --seed 0 --workers 8 --split train
    riskflow-data info data/train
    riskflow-data export data/train/00000-highway.npz --format scenarionet --out exported

``--stop-share P`` makes each recorded vehicle stop once in its lane with probability P
(queues behind it, lane changes around it; :class:`~riskflow_env.scenarios.recording.DriverConfig`).

``generate`` writes scene ``i`` of family ``families[i % len(families)]`` to
``OUT/<i:05d>-<family>.npz`` (maps once each under ``OUT/maps/``), seeded by
``np.random.SeedSequence(seed, spawn_key=(split_key, i))``: the files depend on the
seed, split, families and scene settings, never on the worker count or on which
scenes were made before. Files appear atomically (temp name + rename), so an
interrupted run is resumed by running the same command again: complete scenes are
skipped. One run writes a bank at a time (``OUT/writer.lock``). Workers end as soon as
the parent does (``kill -9`` included), so nothing writes into ``OUT`` once the command
is gone. ``OUT/riskflow-data.json`` records the settings; resuming with different ones
is refused. Scenes per minute are printed at the end.

``export`` writes scene files (RiskFlow ``.npz``, replay files' starting scenes, ScenarioNet
``.pkl``, CommonRoad ``.xml``) in other tools' formats (:mod:`riskflow_env.scenarios.exchange`) as
``OUT/<file stem>.<suffix>``.
"""

from __future__ import annotations

import argparse
import functools
import json
import multiprocessing
import os
import sys
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from riskflow_env.atomic_files import write_text
from riskflow_env.cli_errors import (
    CommandLineParser,
    DefaultsHelpFormatter,
    add_debug_flag,
    user_errors,
)
from riskflow_env.config import check_field_types, is_integer
from riskflow_env.folder_lock import (
    FolderLock,
    FolderLocked,
    check_output_folder,
    make_output_folder,
)
from riskflow_env.maps import FAMILIES
from riskflow_env.processes import MAX_WORKERS, pool_worker
from riskflow_env.scenarios._npz import check_npz_sizes
from riskflow_env.scenarios.folders import commonroad_files, scenarionet_counts
from riskflow_env.scenarios.io import require_scenarios, save_scenario
from riskflow_env.scenarios.naturalistic import SOURCE, SceneConfig, generate_scenario
from riskflow_env.scenarios.recording import DriverConfig
from riskflow_env.scenarios.scenario import MAX_STEPS
from riskflow_env.scenarios.scenarionet_dataset import is_scenarionet_folder
from riskflow_env.state import HISTORY_STEPS

SPLIT_KEYS = {"train": 0, "eval": 1}  # spawn keys: train and eval scenes never share seeds
MANIFEST = "riskflow-data.json"


@dataclass(frozen=True)
class GenerateOptions:
    """Options of ``riskflow-data generate``."""

    out: Path
    """folder of the bank (scene files and maps/)"""
    families: tuple[str, ...] = FAMILIES
    """road families, assigned round-robin to scene indices"""
    scenes: int = 100
    """number of scenes in the bank (indices 0 .. scenes - 1)"""
    seed: int = 0
    """root seed"""
    split: str = "train"
    """'train' or 'eval': separate seed streams"""
    workers: int = 1
    """worker processes (results do not depend on it), at most ``MAX_WORKERS``"""
    future_steps: int = 100
    """reference future per scene [steps of 0.1 s]"""
    stop_share: float = 0.0
    """probability per recorded vehicle that it stops once in its lane (DriverConfig)"""

    def __post_init__(self) -> None:
        check_field_types(self, lambda name: name)
        longest = MAX_STEPS - HISTORY_STEPS  # a scene's tracks hold at most MAX_STEPS
        for name, low, high in (("scenes", 1, None), ("seed", 0, None), ("workers", 1, MAX_WORKERS),
                                ("future_steps", 1, longest)):  # fmt: skip
            value = getattr(self, name)
            if not is_integer(value) or value < low or (high is not None and value > high):
                span = f">= {low}" if high is None else f"in [{low}, {high}]"
                raise ValueError(f"{name} must be an int {span}, got {value!r}")
            object.__setattr__(self, name, int(value))  # a numpy int as a Python one
        if not isinstance(self.stop_share, float | int) or not 0.0 <= self.stop_share <= 1.0:
            raise ValueError(f"stop_share must be a number in [0, 1], got {self.stop_share!r}")
        if self.split not in SPLIT_KEYS:
            raise ValueError(f"split must be one of {tuple(SPLIT_KEYS)}, got {self.split!r}")
        unknown = [family for family in self.families if family not in FAMILIES]
        if unknown or not self.families:
            raise ValueError(f"families must be a non-empty subset of {FAMILIES}, got {unknown}")

    def settings(self) -> dict:
        """What the files depend on (recorded in the manifest; ``stop_share`` only when
        not 0, so banks made before it existed still resume)."""
        settings = {
            "source": SOURCE,
            "families": list(self.families),
            "seed": self.seed,
            "split": self.split,
            "future_steps": self.future_steps,
        }
        if self.stop_share:
            settings["stop_share"] = self.stop_share
        return settings


def scene_path(out: Path, index: int, family: str) -> Path:
    """``out / f"{index:05d}-{family}.npz"``."""
    return out / f"{index:05d}-{family}.npz"


def make_scene(options: GenerateOptions, index: int) -> Path:
    """Generate and write scene ``index`` (what each worker runs)."""
    family = options.families[index % len(options.families)]
    seed = np.random.SeedSequence(options.seed, spawn_key=(SPLIT_KEYS[options.split], index))
    driver = DriverConfig(stop_share=float(options.stop_share))
    config = SceneConfig(future_steps=options.future_steps, driver=driver)
    name = f"{family}-{options.split}-s{options.seed}-{index:05d}"
    scene = generate_scenario(family, np.random.default_rng(seed), config, name=name)
    path = scene_path(options.out, index, family)
    return save_scenario(scene, path, map_dir=options.out / "maps")


def generate(options: GenerateOptions) -> dict:
    """Write the missing scenes of the bank; returns counts and the measured rate.

    One run per bank at a time: a second one into the same ``out`` exits naming the first
    one's pid (:class:`~riskflow_env.folder_lock.FolderLock`), instead of deleting its
    temporary files."""
    lock = FolderLock(options.out)
    try:
        lock.acquire()
    except FolderLocked as err:
        raise SystemExit(f"riskflow-data: {err}") from None
    try:
        return _write_missing(options)
    finally:
        lock.release()


def _write_missing(options: GenerateOptions) -> dict:
    from tqdm import tqdm

    out = options.out
    manifest = out / MANIFEST
    if manifest.exists():
        recorded = json.loads(manifest.read_text())
        settings = options.settings()
        if recorded != settings:
            differ = sorted(
                k for k in set(recorded) | set(settings) if recorded.get(k) != settings.get(k)
            )
            said = ", ".join(
                f"{k}: {recorded.get(k)!r} there, {settings.get(k)!r} now" for k in differ
            )
            raise ValueError(
                f"--out {out} holds a bank made with other settings ({said}): use another "
                "--out or the same settings"
            )
    else:
        write_text(manifest, json.dumps(options.settings(), indent=2) + "\n")
    for stale in [*out.glob(".*.tmp"), *(out / "maps").glob(".*.tmp")]:
        stale.unlink(missing_ok=True)  # left by an interrupted run
    todo = [
        index
        for index in range(options.scenes)
        if not scene_path(out, index, options.families[index % len(options.families)]).exists()
    ]
    skipped = options.scenes - len(todo)
    start = time.perf_counter()
    with tqdm(total=len(todo), desc="scenes", unit="scene", disable=not todo) as bar:
        if options.workers <= 1:
            for index in todo:
                make_scene(options, index)
                bar.update()
        else:
            context = multiprocessing.get_context("spawn")
            processes = min(options.workers, len(todo))
            with context.Pool(processes, initializer=pool_worker) as pool:  # exit: ends it
                for _ in pool.imap_unordered(functools.partial(make_scene, options), todo):
                    bar.update()
    seconds = time.perf_counter() - start
    rate = 60.0 * len(todo) / seconds if todo else 0.0
    print(
        f"riskflow-data: {len(todo)} scenes written in {seconds:.1f} s "
        f"({rate:.1f} scenes/min, {options.workers} worker(s)); {skipped} already on disk"
    )
    return {"written": len(todo), "skipped": skipped, "seconds": seconds, "per_minute": rate}


def info(directory: Path) -> dict[str, int]:
    """Print and return the number of scenes per family in ``directory`` (FileNotFoundError
    when it holds no scene file); per source dataset for a ScenarioNet folder
    (:func:`scenarionet_info`), the file count for CommonRoad scenarios."""
    if is_scenarionet_folder(directory):
        return scenarionet_info(directory)
    commonroad = commonroad_files(directory)
    if commonroad:
        size = sum(path.stat().st_size for path in commonroad)
        print(f"{directory}: {len(commonroad)} CommonRoad scenarios (.xml), {size / 1e6:.1f} MB")
        return {"commonroad": len(commonroad)}
    counts: Counter[str] = Counter()
    agents: Counter[str] = Counter()
    for path in require_scenarios(directory):
        check_npz_sizes(path)  # sizes from the headers before anything is read
        with np.load(path, allow_pickle=False) as data:  # reads only the members used
            family = str(data["family"])
            agents[family] += int(data["length"].shape[0])
        counts[family] += 1
    manifest = directory / MANIFEST
    settings = json.loads(manifest.read_text()) if manifest.exists() else {}
    size = sum(p.stat().st_size for p in directory.rglob("*.npz"))
    print(f"{directory}: {sum(counts.values())} scenes, {size / 1e6:.1f} MB", end="")
    print(f" (split {settings['split']}, seed {settings['seed']})" if settings else "")
    print(f"  {'family':<14}{'scenes':>8}{'mean agents':>13}")
    for family in sorted(counts):
        print(f"  {family:<14}{counts[family]:>8}{agents[family] / counts[family]:>13.1f}")
    return dict(counts)


def scenarionet_info(directory: Path) -> dict[str, int]:
    """:func:`info` of a ScenarioNet dataset folder (:func:`~.folders.scenarionet_counts`)."""
    counts, objects, missing, size = scenarionet_counts(directory)
    print(f"{directory}: {sum(counts.values())} ScenarioNet scenes, {size / 1e6:.1f} MB", end="")
    print(f" ({missing} listed in its summary but missing)" if missing else "")
    print(f"  {'dataset':<14}{'scenes':>8}{'mean objects':>14}")
    for source in sorted(counts):
        name = source if len(source) <= 14 else source[:12] + ".."
        print(f"  {name:<14}{counts[source]:>8}{objects[source] / counts[source]:>14.1f}")
    return dict(counts)


def int_at_least(minimum: int) -> Callable[[str], int]:
    """An argparse ``type``: an int >= ``minimum``, else a usage error naming the option."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < minimum:
            raise argparse.ArgumentTypeError(f"expected an int >= {minimum}, got {text!r}")
        return value

    return parse


def _number(text: str, valid, expected: str) -> float:
    """``text`` as a float accepted by ``valid``, else a usage error saying ``expected``."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not valid(value):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return value


def share(text: str) -> float:
    """An argparse ``type``: a number in [0, 1], else a usage error naming the option."""
    return _number(text, lambda value: 0.0 <= value <= 1.0, "a number in [0, 1]")


def build_parser() -> argparse.ArgumentParser:
    """The ``riskflow-data`` parser (subcommands ``generate``, ``info`` and ``export``)."""
    formatter = DefaultsHelpFormatter
    description = __doc__.split("\n")[0].replace("``", "")  # the docstring's title, plain
    parser = CommandLineParser(
        prog="riskflow-data", description=description, formatter_class=formatter
    )
    commands = parser.add_subparsers(dest="command", required=True)
    gen = commands.add_parser(
        "generate", help="record highway-env IDM/MOBIL scenes", formatter_class=formatter
    )
    gen.add_argument("--out", type=Path, required=True, help="folder of the bank (scenes, maps/)")
    gen.add_argument("--families", nargs="+", choices=FAMILIES, default=list(FAMILIES),
                     help="road families, assigned round-robin to scene indices")  # fmt: skip
    gen.add_argument("--scenes", type=int_at_least(1), default=100,
                     help="number of scenes in the bank (indices 0 .. N-1, generated "
                     "procedurally: any N is made in full)")  # fmt: skip
    gen.add_argument("--seed", type=int_at_least(0), default=0, help="root seed (an int >= 0)")
    gen.add_argument("--split", choices=tuple(SPLIT_KEYS), default="train",
                     help="separate seed streams for train and eval banks")  # fmt: skip
    gen.add_argument("--workers", type=int_at_least(1), default=os.cpu_count() or 1,
                     help="worker processes (results do not depend on it)")  # fmt: skip
    gen.add_argument("--future-steps", type=int_at_least(1), default=100,
                     help="reference future per scene [steps of 0.1 s]")  # fmt: skip
    gen.add_argument("--stop-share", type=share, default=0.0,
                     help="probability per vehicle that it stops once in its lane (a "
                     "breakdown, a drop-off): queues, vehicles passing standing ones")  # fmt: skip
    add_debug_flag(gen)
    show = commands.add_parser(
        "info",
        help="count the scenes of a bank per family (of a ScenarioNet folder per dataset)",
        formatter_class=formatter,
    )
    show.add_argument("directory", type=Path, help="folder of the bank")
    add_debug_flag(show)
    from riskflow_env.scenarios.exchange import FORMATS

    out = commands.add_parser(
        "export", help="write scene files in other tools' formats", formatter_class=formatter
    )
    out.add_argument(
        "files", type=Path, nargs="+", help="scene files (.npz, ScenarioNet .pkl, CommonRoad .xml)"
    )
    out.add_argument("--format", nargs="+", choices=FORMATS, required=True, dest="formats",
                     help="formats to write (docs/how-to/exchange.md)")  # fmt: skip
    out.add_argument("--out", type=Path, required=True, help="folder of the exported files")
    add_debug_flag(out)
    return parser


def output_folder(parser: argparse.ArgumentParser, folder: Path) -> None:
    """Make ``--out`` (and its parents), or exit with a usage error naming it."""
    try:
        make_output_folder(folder, "--out")
    except ValueError as err:
        parser.error(str(err))


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``riskflow-data`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    command = commands.choices[args.command]  # its usage errors name it
    if args.command == "info":
        with user_errors(command.prog, args.debug):
            info(args.directory)
        return 0
    if args.command == "export":
        from riskflow_env.scenarios.exchange import export_files, require_format

        formats = tuple(dict.fromkeys(args.formats))
        for fmt in formats:
            try:
                require_format(fmt)
            except ImportError as err:
                command.error(f"--format {fmt}: {err}")
        try:
            check_output_folder(args.out, "--out")  # made once every input is read
        except ValueError as err:
            command.error(str(err))
        files = list(dict.fromkeys(Path(file).resolve() for file in args.files))  # each once
        with user_errors(command.prog, args.debug):
            written = export_files(files, formats, args.out)
        print(f"riskflow-data: wrote {len(written)} file(s) into {args.out}")
        return 0
    # every field of GenerateOptions is the `generate` argument of the same name
    parsed = {field.name: getattr(args, field.name) for field in fields(GenerateOptions)}
    try:
        options = GenerateOptions(**parsed | {"families": tuple(dict.fromkeys(args.families))})
    except ValueError as err:  # a flag's bound: a usage error naming the flag
        name = str(err).split(" ", 1)[0]
        command.error(f"--{name.replace('_', '-')}{str(err)[len(name) :]}")
    output_folder(command, args.out)
    kept = f"the scenes in {args.out} are kept: the same command resumes"
    with user_errors(command.prog, args.debug, kept):
        generate(options)
    return 0


if __name__ == "__main__":
    sys.exit(main())
