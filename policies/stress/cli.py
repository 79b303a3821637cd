"""``riskflow-stress``: stress-test your planner against the RiskFlow adversary
(docs/tutorials/stress-test.md).

::

    riskflow-stress --planner my_planner.py:plan --scenes 20 --seeds 0 1 2 --workers 2 \\
        --out outputs/stress                      # report.md, report.html, failures/*.npz
    riskflow-stress replay outputs/stress/failures/<scene>-seed0.npz --planner my_planner.py:plan
    riskflow-stress --export scenarionet,openscenario,commonroad ...   # failures in other formats
    riskflow-stress compare idm sampling_mpc --scenes 20 --out outputs/compare

``--planner`` takes a built-in name (idm, sampling_mpc, constant_velocity, lane_keeping,
replay: the logged ego), ``package.module:object`` or ``path/to/file.py:object``
(:mod:`policies.stress.planner_spec`). The options of a run are :class:`RunOptions` (one
flag per field, its docstring as help); bad arguments exit with a usage error naming the
argument.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from policies.dataclass_cli import dataclass_parser
from policies.stress.planner_spec import check_spec
from policies.stress.runner import StressOptions
from riskflow_env.cli_errors import (
    CommandLineParser,
    DefaultsHelpFormatter,
    add_debug_flag,
    user_errors,
)

PROG = "riskflow-stress"
FORMS = "a built-in name, package.module:object or path/to/file.py:object, as --planner"


@dataclass(frozen=True)
class RunOptions(StressOptions):
    """Options of ``riskflow-stress``: the planner and the stress test."""

    planner: str = "idm"
    """the planner under test: a built-in name (idm, sampling_mpc, constant_velocity,
    lane_keeping, replay: the logged ego), package.module:object or path/to/file.py:object
    (a planner callable (observation, view) -> action, or a class or factory called with no
    argument)"""
    export: tuple[str, ...] = ()
    """also write every saved failure (the executed episode) beside its replay file in
    these formats: scenarionet, openscenario, commonroad, comma- or space-separated
    (docs/how-to/exchange.md; the last two need the interop extra)"""

    def __post_init__(self) -> None:
        super().__post_init__()
        check_spec(self.planner, "--planner")  # its form: the planner is loaded by the run
        object.__setattr__(self, "export", export_formats(self.export))


def export_formats(values: Sequence[str]) -> tuple[str, ...]:
    """The formats of ``--export`` values (comma- or space-separated), each checked
    (:func:`riskflow_env.scenarios.exchange.require_format`); ValueError naming --export."""
    from riskflow_env.scenarios.exchange import require_format

    formats = tuple(dict.fromkeys(f for value in values for f in value.split(",") if f))
    for fmt in formats:
        try:
            require_format(fmt)
        except (ImportError, ValueError) as err:
            raise ValueError(f"--export: {err}") from None
    return formats


def export_failures(result: Any, formats: Sequence[str]) -> list[Path]:
    """Write the executed episode of every replay file of ``result`` (a
    :class:`~policies.stress.stress_test.StressResult`) in ``formats`` beside it; returns
    the files written."""
    from riskflow_env.scenarios.exchange import export_scenario

    written = []
    for episode in result.episodes:
        if episode.replay is not None:
            executed = episode.analysed.record.to_scenario()
            for fmt in formats:
                written += export_scenario(executed, episode.replay, fmt)
    return written


def parser() -> argparse.ArgumentParser:
    """The parser of a run (one option per :class:`RunOptions` field)."""
    description = (
        "Stress-test a planner against the RiskFlow adversary; 'riskflow-stress replay FILE' "
        "puts it back into a saved failure, 'riskflow-stress compare A B' pairs two planners."
    )
    return dataclass_parser(RunOptions, PROG, description, debug=True)


COMPARE_OUT = "outputs/stress-compare"  # a plain run's default is outputs/stress


def compare_parser() -> argparse.ArgumentParser:
    """The parser of ``riskflow-stress compare A B`` (the run's options but the planner)."""
    compare = dataclass_parser(
        StressOptions, f"{PROG} compare", "Two planners, paired.", debug=True
    )
    compare.add_argument("a", metavar="PLANNER_A", help=f"planner A: {FORMS}")
    compare.add_argument("b", metavar="PLANNER_B", help="planner B, in the same forms")
    out = next(action for action in compare._actions if action.dest == "out")
    out.help = (
        "output folder: compare.md, compare.json and each planner's run in a-NAME/ and "
        "b-NAME/ (summary.json, report.md, ...; other pairs' folders are kept)"
    )
    compare.set_defaults(out=COMPARE_OUT)
    return compare


def replay_parser() -> argparse.ArgumentParser:
    """The parser of ``riskflow-stress replay FILE``."""
    replay = CommandLineParser(
        prog=f"{PROG} replay",
        description="Re-run a saved failure (closed loop: the same scene, adversary seed and "
        "options) with a planner, and say whether the failure recurs.",
        formatter_class=DefaultsHelpFormatter,
    )
    replay.add_argument("file", help="a replay file (failures/*.npz of a run)")
    replay.add_argument(
        "--planner",
        default=None,
        help=f"the planner to put back: {FORMS} of a run; default: the planner that failed",
    )
    replay.add_argument("--video", default=None, help="write the episode as a .gif or .mp4")
    add_debug_flag(replay)
    return replay


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of ``riskflow-stress``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["replay"]:
        _replay(argv[1:])
    elif argv[:1] == ["compare"]:
        _compare(argv[1:])
    elif argv and not argv[0].startswith("-"):  # a run takes no positional argument
        parser().error(
            f"unknown command {argv[0]!r}: expected 'replay FILE', 'compare A B' or the "
            "options of a run (--planner ...)"
        )
    else:
        _run(argv)


def _options(cls: type, values: dict[str, Any], usage: argparse.ArgumentParser) -> Any:
    try:
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})
    except ValueError as err:
        usage.error(str(err))


def stress_kwargs(options: StressOptions) -> dict[str, Any]:
    """:func:`riskflow_stress`'s keyword arguments of ``options`` (but scenes and seeds)."""
    names = {field.name for field in dataclasses.fields(StressOptions)} - {"scenes", "seeds"}
    return {name: getattr(options, name) for name in names}


def _run(argv: list[str]) -> None:
    from policies.stress.planner_spec import PlannerSpecError
    from policies.stress.runner import SceneSourceError
    from policies.stress.stress_test import riskflow_stress

    usage = parser()
    values = vars(usage.parse_args(argv))
    debug = values.pop("debug")
    options = _options(RunOptions, values, usage)
    with user_errors(PROG, debug):  # the usage errors below first
        try:
            result = riskflow_stress(
                options.planner, options.scenes, options.seeds, **stress_kwargs(options)
            )
        except PlannerSpecError as err:
            usage.error(err.named("--planner"))
        except SceneSourceError as err:
            usage.error(str(err))
    print(result.headline)
    replays = (
        f"{len(result.replays)} replay file(s) in {result.out}/failures/"
        if result.replays
        else "no failure, no replay file"
    )
    print(f"wrote {result.out}/report.html, report.md, summary.json; {replays}")
    formats = options.export
    if formats and result.replays:
        with user_errors(PROG, debug):
            exported = export_failures(result, formats)
        print(f"exported {len(exported)} file(s) ({', '.join(formats)}) beside the replay files")


def _compare(argv: list[str]) -> None:
    from policies.stress.compare import compare, markdown
    from policies.stress.planner_spec import PlannerSpecError
    from policies.stress.runner import SceneSourceError

    usage = compare_parser()
    values = vars(usage.parse_args(argv))
    a, b, debug = values.pop("a"), values.pop("b"), values.pop("debug")
    options = _options(StressOptions, values, usage)
    with user_errors(usage.prog, debug):  # the usage errors below first
        try:
            table = compare(a, b, options.scenes, options.seeds, **stress_kwargs(options))
        except PlannerSpecError as err:
            usage.error(err.named("PLANNER_A" if err.spec == a else "PLANNER_B"))
        except SceneSourceError as err:
            usage.error(str(err))
    print(markdown(table))
    runs = " and ".join(f"{options.out}/{name}/" for name in table["folders"].values())
    print(f"wrote {options.out}/compare.md, compare.json and the runs' reports in {runs}")


def _replay(argv: list[str]) -> None:
    from policies.stress.planner_spec import PlannerSpecError, load_planner
    from policies.stress.replay import load_replay, replay
    from riskflow_env.wrappers.video import check_video_path

    usage = replay_parser()
    args = usage.parse_args(argv)
    try:
        if args.video is not None:
            check_video_path(args.video, "--video")
    except ValueError as err:
        usage.error(str(err))
    try:
        saved = load_replay(args.file)
    except (OSError, ValueError) as err:
        usage.error(f"file: {err}")
    spec = args.planner or saved.meta["planner"]
    try:
        planner = load_planner(spec, saved.setup.env_config().dynamics)
    except PlannerSpecError as err:
        hint = "" if args.planner else " (the saved planner; give --planner)"
        usage.error(err.named("--planner") + hint)
    with user_errors(usage.prog, args.debug):
        result = replay(saved, planner, video=args.video)
    print(result.describe())
    if args.video:
        print(f"wrote {args.video}")


if __name__ == "__main__":
    main()
