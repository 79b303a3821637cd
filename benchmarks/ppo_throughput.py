"""PPO decisions per second of the ego recipe: subprocess envs vs the vector env.

How many more decisions the PPO ego recipe trains on in the same wall time when its envs
are stepped as one vector env. Each row runs ``examples/train_ego_ppo.py`` as a user
would, with the recipe's options (its adversary, curriculum, interface and PPO
hyperparameters) and one way of stepping the envs, for ``--decisions`` decisions, one
row after the other in one run:

* **recipe**: ``--vec-env subproc --num-envs 2`` (one process and one adversary per env,
  SB3's ``SubprocVecEnv``; 2 x 512 decisions per update);
* **vector**: ``--vec-env batched --num-envs 16 --n-steps 64`` (one ``EgoVectorEnv``, one
  adversary call per cycle for all scenes, one process; the same update size);
* **vector-shards2**: the same 16 scenes split over 2 worker processes
  (``--shards 2``, :mod:`policies.rl.sb3_shards`);
* **vector32-shards2**: ``--num-envs 32 --n-steps 32 --shards 2``.

Reported per row: SB3's ``time/fps`` at the end of training (decisions per second of
``learn``: env steps and PPO updates, without start-up), the command's wall time, and
the ratio of decisions/s to the recipe's. ``--maneuver-set mpc`` and other recipe
options can be given through ``--extra``.

    python benchmarks/ppo_throughput.py [--decisions 4096] [--extra "--maneuver-set mpc"]
"""

from __future__ import annotations

import csv
import shlex
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from policies.dataclass_cli import check_at_least, parse_dataclass, passed_options
from riskflow_env.cli_errors import run_script

ROOT = Path(__file__).resolve().parents[1]
ROWS = {
    "recipe": ["--vec-env", "subproc", "--num-envs", "2"],
    "vector": ["--vec-env", "batched", "--num-envs", "16", "--n-steps", "64"],
    "vector-shards2": ["--vec-env", "batched", "--num-envs", "16", "--n-steps", "64",
                         "--shards", "2"],
    "vector32-shards2": ["--vec-env", "batched", "--num-envs", "32", "--n-steps",
                                    "32", "--shards", "2"],
}  # fmt: skip
# what a row's name stands for, and what the benchmark sets: not for --extra to change
ROW_OPTIONS = ("--vec-env", "--num-envs", "--shards", "--total-timesteps", "--seed", "--out")


@dataclass(frozen=True)
class Options:
    """Benchmark options."""

    decisions: int = 4096
    """decisions (env steps of all envs together) each row trains for"""
    rows: tuple[str, ...] = tuple(ROWS)
    """which rows to run (the first one given is the ratios' reference)"""
    extra: str = ""
    """more train_ego_ppo.py options for every row, e.g. "--maneuver-set mpc" """
    seed: int = 0
    """the runs' seed"""

    def __post_init__(self) -> None:
        check_at_least(self, {"decisions": 1, "seed": 0}, highs={"seed": 2**32 - 1})
        unknown = [row for row in self.rows if row not in ROWS]
        if unknown or not self.rows:
            raise ValueError(f"--rows must be some of {list(ROWS)}, got {list(self.rows)}")
        passed_options(self.extra, "--extra", ROW_OPTIONS, "the rows and the benchmark set them")


def run_row(name: str, options: Options, out: Path) -> dict:
    """Train one row; its decisions/s (SB3's last ``time/fps``) and wall time [s]."""
    command = [
        sys.executable, str(ROOT / "examples" / "train_ego_ppo.py"), *ROWS[name],
        "--total-timesteps", str(options.decisions), "--checkpoint-every", "0",
        "--seed", str(options.seed), "--out", str(out), *shlex.split(options.extra),
    ]  # fmt: skip
    start = time.perf_counter()
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"row {name!r} failed: {shlex.join(command)}\n{done.stderr[-3000:]}")
    with open(out / "progress.csv", newline="") as handle:
        last = list(csv.DictReader(handle))[-1]
    return {
        "row": name,
        "fps": float(last["time/fps"]),
        "decisions": int(float(last["time/total_timesteps"])),
        "wall": wall,
    }


def main(argv: list[str] | None = None) -> list[dict]:
    """Print the table; returns its rows (``row``, ``fps``, ``decisions``, ``wall`` [s])."""
    options = parse_dataclass(
        Options, argv, prog="ppo_throughput.py", description=__doc__, debug=True
    )
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for index, name in enumerate(options.rows):
            rows.append(run_row(name, options, Path(folder) / f"row{index}"))
            print(f"  {name}: {rows[-1]['fps']:.1f} decisions/s", flush=True)
    reference = rows[0]["fps"]
    print(f"\n{'way of stepping':<30}{'decisions/s':>13}{'decisions':>11}{'wall s':>9}{'ratio':>8}")
    for row in rows:
        ratio = row["fps"] / reference
        print(
            f"{row['row']:<30}{row['fps']:>13.1f}{row['decisions']:>11}{row['wall']:>9.1f}"
            f"{ratio:>7.2f}x"
        )
    print(
        f"\ndecisions/s = SB3's time/fps at the end of learn (env steps and PPO updates); "
        f"ratio = row / {rows[0]['row']}; extra options: {options.extra or '(none)'}"
    )
    return rows


if __name__ == "__main__":
    run_script("ppo_throughput.py", main)
