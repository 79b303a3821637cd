"""``riskflow-train``: train a generator on a scenario bank (MeanFlow or diffusion).

::

    riskflow-data generate --out data/train --scenes 626 --split train --seed 0
    riskflow-data generate --out data/val --scenes 140 --split eval --seed 1
    riskflow-train --data data/train --val-data data/val --out runs/riskflow --lr 5e-4
    riskflow-train --recipe riskflow-default  # the shipped checkpoint's run (README)
    torchrun --standalone --nproc_per_node 2 --no-python riskflow-train --recipe ...

Under ``torchrun`` it trains data-parallel: ``--batch-size`` is the global batch, split
across the processes (:mod:`policies.learned.distributed`; docs/how-to/train-generator.md).

``--recipe NAME_OR_PATH`` starts from a recipe file's values (:mod:`policies.recipes`:
one per shipped checkpoint); the options given beside it override them.

The loop (batches, Adam, clipping, EMA, validation, checkpoints, ``--resume``) is
:func:`policies.learned.trainer.fit`; this command picks the objective it runs:

* ``--generator meanflow`` (default): RiskFlow's MeanFlow objective
  (:class:`~policies.riskflow.meanflow.MeanFlowObjective`; times from
  ``TimeSampler``: logit-normal, ``r = t`` for 20 %, always with ``--flow-matching``;
  ``--one-step-fraction`` puts a share at the sampler's own call ``(0, 1)``).
  The loss is the trajectory-space error plus ``action_weight`` (default 1) times the
  normalised action error: positions barely see high-frequency action noise, so without
  it one-step plans keep the noise of ``eps`` (pilot: jerk 16 m/s^3 against 4.6 with it,
  the data's 7.2; ADE 1.58 against 1.51 m).
* ``--generator diffusion``: the DDPM denoiser of the CTG / CTG++ / CCDiff-style
  baselines (:class:`~policies.baselines.diffusion.train.DiffusionObjective`; same
  network, data, EMA and validation; docs/how-to/baselines.md).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from policies.baselines.diffusion.model import PREDICTIONS
from policies.baselines.diffusion.schedule import SCHEDULES
from policies.baselines.diffusion.train import DiffusionObjective
from policies.dataclass_cli import Recipes, dataclass_parser, parse_dataclass
from policies.learned.train_options import LoopOptions
from policies.learned.trainer import CHECKPOINT, GENERATOR, METRICS_LOG, fit
from policies.recipes import read_recipe, shipped_recipes
from policies.riskflow.meanflow import MeanFlowObjective
from policies.riskflow.time_sampler import TimeSampler
from riskflow_env.cli_errors import debug_requested, user_errors

GENERATORS = ("meanflow", "diffusion")
PROG = "riskflow-train"


@dataclass(frozen=True)
class TrainOptions(LoopOptions):
    """Options of ``riskflow-train``: the loop's, then the generator's."""

    flow_matching: bool = False
    """train the plain flow-matching reference (r = t always, sampled in one Euler step)"""
    generator: str = "meanflow"
    """'meanflow' (RiskFlow) or 'diffusion' (the DDPM of the CTG/CTG++/CCDiff baselines)"""
    diffusion_steps: int = 100
    """--generator diffusion: number of diffusion levels K"""
    diffusion_schedule: str = "cosine"
    """--generator diffusion: noise schedule, 'cosine' or 'linear'"""
    diffusion_prediction: str = "v"
    """--generator diffusion: parameterisation, 'v' (x0 with a skip), 'sample' (x0) or 'epsilon'"""
    val_sampling_steps: int = 10
    """--generator diffusion: deterministic DDIM levels of the validation samples"""
    equal_fraction: float = 0.2
    """share of MeanFlow samples with r = t"""
    one_step_fraction: float = 0.0
    """share of MeanFlow samples at the sampler's own call (t, r) = (0, 1)"""

    def rules(self) -> dict[str, bool]:
        """The loop's checks and the generator options'."""
        return super().rules() | {
            f"--generator in {GENERATORS}": self.generator in GENERATORS,
            f"--diffusion-schedule in {SCHEDULES}": self.diffusion_schedule in SCHEDULES,
            f"--diffusion-prediction in {PREDICTIONS}": self.diffusion_prediction in PREDICTIONS,
            "--flow-matching only with --generator meanflow": not (
                self.flow_matching and self.generator != "meanflow"
            ),
            "--equal-fraction, --one-step-fraction in [0, 1]": all(
                0.0 <= share <= 1.0 for share in (self.equal_fraction, self.one_step_fraction)
            ),
            "--one-step-fraction only with --generator meanflow, without --flow-matching": not (
                self.one_step_fraction and (self.flow_matching or self.generator != "meanflow")
            ),
            "--diffusion-steps, --val-sampling-steps >= 1": min(
                self.diffusion_steps, self.val_sampling_steps
            )
            >= 1,
        }


def objective(options: TrainOptions) -> MeanFlowObjective | DiffusionObjective:
    """The objective of ``options.generator``."""
    if options.generator == "diffusion":
        return DiffusionObjective.from_options(options)
    times = TimeSampler(
        equal_fraction=options.equal_fraction,
        flow_matching=options.flow_matching,
        one_step_fraction=options.one_step_fraction,
    )
    return MeanFlowObjective(times, flow_matching=options.flow_matching)


def train(options: TrainOptions) -> dict[str, Any]:
    """Train (or, with ``options.resume``, continue); returns the last metrics logged."""
    return fit(options, objective(options))


def _recipes() -> Recipes:
    return Recipes(read_recipe, shipped_recipes())


def parser() -> argparse.ArgumentParser:
    """The ``riskflow-train`` command line (``--help``)."""
    return dataclass_parser(TrainOptions, PROG, __doc__.split("\n")[0], _recipes(), debug=True)


def parse_options(argv: Sequence[str] | None = None) -> TrainOptions:
    """``riskflow-train``'s options from ``argv`` (``sys.argv[1:]`` if None): a
    ``--recipe``'s values, then the options given (a usage error names what is wrong)."""
    return parse_dataclass(TrainOptions, argv, PROG, __doc__.split("\n")[0], _recipes(), debug=True)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``riskflow-train`` console script."""
    argv = sys.argv[1:] if argv is None else list(argv)
    options = parse_options(argv)
    kept = f"--resume goes on from the last checkpoint in {options.out}, if one was written"
    with user_errors(PROG, debug_requested(argv), kept):
        train(options)
    return 0


__all__ = [
    "CHECKPOINT",
    "GENERATOR",
    "METRICS_LOG",
    "TrainOptions",
    "main",
    "objective",
    "parse_options",
    "parser",
    "train",
]

if __name__ == "__main__":
    sys.exit(main())
