"""``riskflow-eval``: closed-loop evaluation of the adversaries and baselines
(docs/tutorials/reproduce.md).

::

    riskflow-eval --methods riskflow ctg idm --k 2 5 all --interval 0.5 --scenes 100 \\
        --workers 2 --out outputs/eval          # runs what is missing, then writes the report
    riskflow-eval report --out outputs/eval     # the report alone
    riskflow-eval --list                        # the methods

The options are :class:`~policies.evaluation.options.EvalOptions` (one flag per field,
its docstring as help; tuple fields take several values). Bad arguments exit with a
usage error naming the argument; a bad file met while running exits with one line
(``--debug`` shows the traceback).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from policies.dataclass_cli import dataclass_parser
from policies.evaluation.options import EvalOptions
from policies.registry import method_list
from riskflow_env.cli_errors import (
    CommandLineParser,
    DefaultsHelpFormatter,
    add_debug_flag,
    user_errors,
)

PROG = "riskflow-eval"


def parser() -> argparse.ArgumentParser:
    """The run parser: one option per :class:`EvalOptions` field, plus ``--list``."""
    description = (
        "Closed-loop evaluation; 'riskflow-eval report --out DIR' writes the report of a "
        "results folder."
    )
    parser = dataclass_parser(EvalOptions, PROG, description, debug=True)
    parser.add_argument("--list", action="store_true", help="list the methods and exit")
    return parser


def report_parser() -> argparse.ArgumentParser:
    """The parser of ``riskflow-eval report``."""
    report = CommandLineParser(
        prog=f"{PROG} report", formatter_class=DefaultsHelpFormatter
    )
    report.add_argument("--out", required=True, help="results folder of a riskflow-eval run")
    report.add_argument("--no-plots", action="store_true", help="tables only")
    add_debug_flag(report)
    return report


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of ``riskflow-eval``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    from policies.evaluation.report import write_report  # after argv: --help stays fast

    if argv[:1] == ["report"]:
        report = report_parser()
        args = report.parse_args(argv[1:])
        with user_errors(report.prog, args.debug):
            print(f"wrote {write_report(args.out, plots=not args.no_plots)}")
        return
    run_parser = parser()
    args = vars(run_parser.parse_args(argv))
    debug = args.pop("debug")
    if args.pop("list"):
        print(method_list())
        return
    from policies.evaluation.runner import prepare, run_evaluation

    values = {k: tuple(v) if isinstance(v, list) else v for k, v in args.items()}
    try:  # the values, then the scenes and the output folder
        options = EvalOptions(**values)
        prepared = prepare(options)
    except ValueError as err:
        run_parser.error(str(err))
    kept = f"the rollouts in {options.out}/results.jsonl are kept: the same command resumes"
    with user_errors(PROG, debug, kept):
        summary = run_evaluation(options, prepared=prepared)
        print(
            f"{summary['ran']} rollouts run in {summary['wall_s']:.1f} s "
            f"({summary['skipped']} of {summary['planned']} were already in {options.out})"
        )
        if options.report:
            print(f"wrote {write_report(options.out)}")


if __name__ == "__main__":
    main()
