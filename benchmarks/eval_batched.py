"""``riskflow-eval`` per-scene vs batched: the wall time of one evaluation both ways, in one run.

Runs the same evaluation (default: the 100-scene K = 5 evaluation of ``riskflow`` as it
ships, 10 s episodes, IDM ego; ``--methods`` takes any of ``riskflow-eval --list``, e.g.
``riskflow-raw``) with ``riskflow-eval``, each in a fresh process of its own, one after
the other:

* **per-scene**: ``--batch-scenes 1``, one ``ClosedLoop`` rollout at a time;
* **batched**: ``--batch-scenes N`` for each N of ``--batch``: N scenes stepped by one
  ``SceneBatch`` transition, the adversary planning every scene due in one call.

Reported per way: the rollouts' wall time (what ``riskflow-eval`` prints: warm-up and
metrics included, start-up and imports not), the command's wall time, and the ratio of
the per-scene time to each; then how far the batched rows are from the per-scene rows of
the same jobs (they match to float rounding, which a long closed-loop rollout can
amplify: the largest difference of a row's numbers, and the rows whose outcome differs)
and the evaluation's metrics from each run (``riskflow-eval report``'s table).

``--perturb STD`` adds a reference: the per-scene path once more, with Gaussian noise of
standard deviation STD (normalised action units; 3e-7 is about the rounding by which a
batched generator pass differs from a one-scene pass) added to the MeanFlow generator's
base residual ``u0`` at every planning cycle. Its rows differ from the per-scene rows as
much as rounding alone can make a closed-loop rollout differ, so the batched rows'
differences can be read against it (docs/explanation/speed.md). MeanFlow methods only,
in one process (``--workers 1``).

    python benchmarks/eval_batched.py [--scenes 100] [--batch 100] [--duration 10]
        [--perturb 3e-7]
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

from policies.dataclass_cli import parse_dataclass
from policies.evaluation import ResultsStore, build_tables
from riskflow_env.cli_errors import run_script

ROOT = Path(__file__).resolve().parents[1]
SUMMARY = re.compile(r"(\d+) rollouts run in ([\d.]+) s")
OUTCOME = ("steps", "collision", "ego_collision", "first_collision_step")  # discrete results
METRICS = {
    "scr": "SCR", "ego_collision_rate": "ego SCR", "orr": "ORR", "orr_footprint": "ORR fp",
    "ade": "ADE", "fde": "FDE", "kdd": "KDD", "wosac": "WOSAC",
}  # fmt: skip
CLOSE = 1e-3  # a row whose numbers all lie within this of the per-scene row's is "close"


@dataclass(frozen=True)
class Options:
    """Benchmark options."""

    scenes: int = 100
    """shipped evaluation scenes (the first ones)"""
    batch: tuple[int, ...] = (100,)
    """--batch-scenes values of the batched runs"""
    methods: tuple[str, ...] = ("riskflow",)
    """methods evaluated"""
    k: str = "5"
    """controllable-set size K"""
    duration: float = 10.0
    """[s] episode length"""
    workers: int = 1
    """--workers of every run"""
    diffusion_steps: int | None = None
    """--diffusion-steps of the diffusion baselines (None: all 100, DDPM)"""
    out: str | None = None
    """folder for the runs' results (default: a temporary folder, removed at the end)"""
    perturb: float | None = None
    """std of the noise on the generator's u0 in one more per-scene run (None: no such run)"""


# ``python -c`` program of the perturbed per-scene run: riskflow-eval in this process with
# the MeanFlow generator's base residual perturbed (argv: STD, then riskflow-eval's own)
PERTURBED = """
import sys
import torch
import policies.pipeline.stages as policy
from policies.evaluation.cli import main
std, base = float(sys.argv[1]), policy.base_velocity
draw = torch.Generator().manual_seed(0)
def perturbed(model, eps, scene):
    u0 = base(model, eps, scene)
    return u0 + std * torch.randn(u0.shape, generator=draw, dtype=u0.dtype)
policy.base_velocity = perturbed
main(sys.argv[2:])
"""


PROG = "eval_batched.py"  # the name in usage and error lines


def _parse(argv: list[str] | None = None) -> Options:
    options = parse_dataclass(
        Options, argv, prog=PROG, description=__doc__.split("\n")[0], debug=True
    )
    batches, out = options.batch, options.out
    if any(batch < 2 for batch in batches) or len(set(batches)) < len(batches):
        _usage(f"--batch: distinct values >= 2 (1 is the per-scene run), got {list(batches)}")
    if out is not None and Path(out).is_dir() and any(Path(out).iterdir()):
        _usage(f"--out {out} is not empty: every timed run starts in a new folder")
    if options.perturb is not None:
        from policies.registry import METHODS

        if not (math.isfinite(options.perturb) and options.perturb > 0):
            _usage(f"--perturb must be a finite number > 0, got {options.perturb}")
        if options.workers != 1:
            _usage(f"--perturb needs --workers 1 (one process), got {options.workers}")
        diffusion = [name for name in options.methods if METHODS[name].diffusion]
        if diffusion:
            _usage(f"--perturb takes MeanFlow methods only, got {diffusion}")
    return options


def _usage(message: str) -> NoReturn:
    raise SystemExit(f"{PROG}: error: {message}")


def run_eval(options: Options, batch: int, out: Path, perturb: float | None = None) -> dict:
    """One ``riskflow-eval`` run in a fresh process; its rollout and command wall times.
    ``perturb``: the per-scene run with the generator's ``u0`` perturbed (``PERTURBED``)."""
    program = ["-m", "policies.evaluation.cli"]
    if perturb is not None:
        program = ["-c", PERTURBED, repr(perturb)]
    argv = [
        sys.executable, *program, "--methods", *options.methods,
        "--k", options.k, "--scenes", str(options.scenes), "--duration", str(options.duration),
        "--workers", str(options.workers), "--batch-scenes", str(batch), "--no-report",
        "--out", str(out),
    ]  # fmt: skip
    if options.diffusion_steps is not None:
        argv += ["--diffusion-steps", str(options.diffusion_steps)]
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    start = time.perf_counter()
    result = subprocess.run(argv, capture_output=True, text=True, env=env, cwd=ROOT)
    command = time.perf_counter() - start
    match = SUMMARY.search(result.stdout)
    if result.returncode == 2:  # a user error (a bad --out, ...): riskflow-eval's one line
        lines = result.stderr.strip().splitlines() or ["(no message)"]
        raise ValueError(lines[-1].removeprefix("riskflow-eval: error: "))
    if result.returncode != 0 or match is None:
        raise RuntimeError(f"riskflow-eval failed ({result.returncode}):\n{result.stderr[-2000:]}")
    label = batch if perturb is None else f"1+{perturb:g}"
    return {"batch": label, "rollouts": int(match[1]), "rollout_s": float(match[2]),
            "command_s": command, "out": out}  # fmt: skip


def _numbers(row: dict, prefix: str = "") -> dict[str, float]:
    """A row's numbers (timings and file names left out), flattened."""
    found = {}
    for key, value in row.items():
        if key in ("timing", "samples"):
            continue
        if isinstance(value, dict):
            found |= _numbers(value, f"{prefix}{key}.")
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            found[prefix + key] = float(value)
    return found


def compare(reference: Path, other: Path) -> dict:
    """The largest difference of the rows' numbers and the rows whose outcome differs."""
    first = {row["key"]: row for row in ResultsStore(reference).rows()}
    second = {row["key"]: row for row in ResultsStore(other).rows()}
    return compare_rows(first, second)


def compare_rows(first: dict[str, dict], second: dict[str, dict]) -> dict:
    """:func:`compare` of two runs' rows by key. A number that one row has and the other
    has not (a time to the ego's first collision where only one run's ego collided) makes
    the rows apart; the largest difference is over the numbers both have."""
    largest, apart, outcome = 0.0, 0, 0
    for key, row in first.items():
        mine, theirs = _numbers(row), _numbers(second[key])
        shared = [name for name in mine if name in theirs and math.isfinite(mine[name])]
        gaps = [abs(mine[name] - theirs[name]) for name in shared]
        largest = max([largest, *gaps])
        apart += max(gaps, default=0.0) > CLOSE or mine.keys() != theirs.keys()
        outcome += any(row.get(name) != second[key].get(name) for name in OUTCOME)
    return {"max_diff": largest, "apart": apart, "outcome_differs": outcome, "rows": len(first)}


def main(argv: list[str] | None = None) -> list[dict]:
    """Print the table; returns its rows (``batch``, ``rollouts``, ``rollout_s``,
    ``command_s``, and for the batched runs ``max_diff`` / ``outcome_differs``)."""
    options = _parse(argv)
    steps = options.diffusion_steps
    print(
        f"riskflow-eval --methods {' '.join(options.methods)} --k {options.k} --scenes "
        f"{options.scenes} --duration {options.duration} --workers {options.workers}"
        f"{'' if steps is None else f' --diffusion-steps {steps}'}: per-scene "
        f"(--batch-scenes 1) vs batched, each in a fresh process, one after the other\n"
    )
    with tempfile.TemporaryDirectory() as temporary:
        folder = Path(options.out or temporary)
        rows = [run_eval(options, 1, folder / "batch1")]
        for batch in options.batch:
            row = run_eval(options, batch, folder / f"batch{batch}")
            rows.append(row | compare(rows[0]["out"], row["out"]))
        if options.perturb is not None:
            row = run_eval(options, 1, folder / "perturbed", options.perturb)
            rows.append(row | compare(rows[0]["out"], row["out"]))
        for row in rows:
            table = build_tables(ResultsStore(row.pop("out")))[0]
            row["label"], row["metrics"] = next(iter(table.metrics.items()))
    print(
        f"{'batch-scenes':>12}{'rollouts':>10}{'rollouts [s]':>14}{'command [s]':>13}"
        f"{'ratio':>8}{'max |diff|':>12}{'rows > 1e-3':>13}{'outcome differs':>17}"
    )
    base = rows[0]["rollout_s"]
    for row in rows:
        diff = f"{row['max_diff']:.1e}" if "max_diff" in row else "-"
        differs = f"{row['outcome_differs']} of {row['rows']}" if "rows" in row else "-"
        apart = f"{row['apart']} of {row['rows']}" if "rows" in row else "-"
        # riskflow-eval prints its rollout time to 0.1 s: a tiny run may read 0
        ratio = f"{base / row['rollout_s']:.2f}x" if row["rollout_s"] > 0 else "n/a"
        print(
            f"{row['batch']:>12}{row['rollouts']:>10}{row['rollout_s']:>14.1f}"
            f"{row['command_s']:>13.1f}{ratio:>8}{diff:>12}{apart:>13}{differs:>17}"
        )
    print(
        "\nrollouts [s]: riskflow-eval's rollout wall time; command: the process's (start-up "
        "included); ratio = per-scene rollouts / these; max |diff|: largest difference of a "
        "row's numbers from the per-scene row of the same job; rows > 1e-3: rows with a number "
        "further than that; outcome differs: rows whose steps or collision flags differ"
        + (
            f"; 1+{options.perturb:g}: the per-scene path with noise of that std on the "
            "generator's u0 (the closed loop's own sensitivity to rounding)"
            if options.perturb is not None
            else ""
        )
    )
    width = max([12, *(len(row["label"]) + 2 for row in rows)])  # labels carry options
    print(
        f"\n{'batch-scenes':>12}{'method':>{width}}"
        + "".join(f"{name:>9}" for name in METRICS.values())
    )
    for row in rows:
        print(f"{row['batch']:>12}{row['label']:>{width}}" + "".join(
            f"{row['metrics'][name]:>9.4f}" for name in METRICS
        ))  # fmt: skip
    print("\nthe metrics of each run, as its report gives them (riskflow-eval report)")
    return rows


if __name__ == "__main__":
    run_script(PROG, main)
