"""Options of the training loop (``riskflow-train``'s shared flags), the learning-rate
schedule and the model configuration they name; the loop itself is
:func:`policies.learned.trainer.fit`."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

from policies.cli_inputs import check_device
from policies.dataclass_cli import check_at_least, check_field_types, flag_of
from policies.learned.config import ModelConfig
from policies.learned.recovery import RecoveryConfig
from riskflow_env.folder_lock import check_output_folder
from riskflow_env.processes import MAX_THREADS

LR_SCHEDULES = ("constant", "cosine")
MAX_STEPS = 10**8  # [-] largest --steps (the shipped recipe trains 8,000)
MAX_SEED = 2**32 - 1  # numpy's largest seed
LOSS_WEIGHTS = (  # the weights of the loss's terms (each finite and >= 0)
    "action_weight", "heading_weight", "collision_weight", "offroad_weight", "jerk_weight"
)  # fmt: skip


@dataclass(frozen=True)
class LoopOptions:
    """Options of the training loop (``riskflow-train`` adds the generator's)."""

    data: tuple[Path, ...]
    """training scenes: a folder written by `riskflow-data generate`, or a ScenarioNet dataset
    folder (recorded scenes, read one at a time with their tracks smoothed when the windows
    are cut); several folders (--data A B, or --data repeated) train on all their scenes
    together (then --val-data is needed) (required, unless --recipe gives it)"""
    data_weights: tuple[float, ...] = ()
    """one per --data folder: its share of each epoch's windows is its weight over their sum
    (none: each folder's share of the windows)"""
    out: Path = Path("runs/riskflow")
    """output folder: checkpoint.pt (resumable), generator.pt (to ship), metrics.jsonl"""
    val_data: Path | None = None
    """validation scenario directory; without it --val-fraction of --data's scenes"""
    val_fraction: float = 0.1
    """share of --data's scenes held out for validation when --val-data is not given"""
    steps: int = 8000
    """optimiser steps in all (a resumed run continues up to this)"""
    batch_size: int = 16
    """windows (scenes) per batch"""
    lr: float = 1e-4
    """Adam learning rate (the peak, with --lr-schedule cosine)"""
    lr_schedule: str = "constant"
    """'constant', or 'cosine': linear warm-up over --warmup-steps, then a cosine decay
    to 0 at --steps (SGDR, Loshchilov & Hutter 2017, without restarts)"""
    warmup_steps: int = 0
    """steps of linear learning-rate warm-up from 0 (with --lr-schedule cosine)"""
    ema_decay: float = 0.995
    """EMA decay of the weights per step"""
    grad_clip: float = 1.0
    """maximum global gradient norm (inf: no clipping)"""
    action_weight: float = 1.0
    """weight of the normalised action MSE added to the trajectory-space loss (smooth plans)"""
    heading_weight: float = 0.0
    """weight [m^2/rad^2] of the heading MSE in the trajectory-space loss"""
    collision_weight: float = 0.0
    """weight of the squared penetration depth of decoded box pairs [m^2] (plan_penalties)"""
    offroad_weight: float = 0.0
    """weight of the squared SDF excess of planned centres over the reference's [m^2]"""
    jerk_weight: float = 0.0
    """weight [m s^3] of the decoded plans' mean absolute longitudinal jerk [m/s^3]
    (plan_penalties.jerk_penalty: an L1 term against step-to-step acceleration noise)"""
    model: str = ""
    """ModelConfig fields as JSON, or a .json file holding them (empty: defaults)"""
    stride: int = 5
    """steps between the current steps of consecutive windows of a scene"""
    bucket: int = 32
    """batches per pool sorted by agent count (less padding); 1: plain shuffling"""
    eval_every: int = 500
    """steps between validations (and checkpoints)"""
    val_windows: int = 512
    """validation windows used (a fixed subset; 0: all)"""
    num_samples: int = 6
    """samples per agent for minADE / minFDE"""
    log_every: int = 50
    """steps between lines in metrics.jsonl"""
    seed: int = 0
    """seed of the model initialisation, batch order, noise and times"""
    threads: int = 1
    """torch CPU threads (0: torch's default); 1 avoids oversubscribing a small machine"""
    device: str = "cpu"
    """'cpu' or 'cuda' (or 'cuda:N')"""
    resume: bool = False
    """continue from OUT/checkpoint.pt"""
    init: Path | None = None
    """fine-tune: start from this generator checkpoint's weights (model and EMA), model
    config and action statistics, with a fresh optimiser (ignored with --resume)"""
    recovery_copies: int = 0
    """recovery windows per training window: agents drift off their log and return
    (policies.learned.recovery; ChauffeurNet-style perturbations)"""
    recovery_offset: float = 1.0
    """largest lateral drift of a recovery window's agents [m]"""
    recovery_parked: int = 0
    """cars parked beside the road added to each recovery window (policies.learned.parked)"""
    recovery_parked_turn: float = 0.0
    """share of the cars parked beside the road (--recovery-parked) that stand across it, as
    in a car park (learned.parked)"""
    recovery_parked_jitter: float = 0.0
    """largest noise level [m/s] of the parked cars' logged history: they creep back and
    forth before the current step, as annotated parked cars do (learned.parked)"""
    time_budget_min: float = 0.0
    """stop cleanly and save after this many minutes of this run (0: no limit)"""
    stop_step: int = 0
    """end the run at this step (0: at --steps), on --steps' learning-rate schedule: repeats
    a run that its time budget stopped, on any machine (docs/how-to/train-generator.md)"""

    def rules(self) -> dict[str, bool]:
        """``{rule: holds}`` of the option checks (subclasses add theirs)."""
        return {
            "--lr finite and > 0": math.isfinite(self.lr) and self.lr > 0,
            "--time-budget-min finite and >= 0 (0: no limit)": math.isfinite(self.time_budget_min)
            and self.time_budget_min >= 0,
            f"--lr-schedule in {LR_SCHEDULES}": self.lr_schedule in LR_SCHEDULES,
            "0 <= --warmup-steps < --steps": 0 <= self.warmup_steps < self.steps,
            "0 <= --stop-step <= --steps": 0 <= self.stop_step <= self.steps,
            "--grad-clip > 0": self.grad_clip > 0,
            "0 <= --ema-decay < 1": 0 <= self.ema_decay < 1,
            "0 < --val-fraction < 1": 0 < self.val_fraction < 1,
            f"--val-data with several --data folders (got {len(self.data)} and no --val-data)"
            if len(self.data) > 1
            else "--data: at least one folder": len(self.data) == 1
            or (len(self.data) > 1 and self.val_data is not None),
            _weights_rule(self.data_weights, len(self.data)): not self.data_weights
            or (
                len(self.data_weights) == len(self.data) > 1
                and all(math.isfinite(w) and w > 0 for w in self.data_weights)
            ),
            "--recovery-copies, --recovery-parked >= 0": self.recovery_copies >= 0
            and self.recovery_parked >= 0,
            "--recovery-offset >= 0": math.isfinite(self.recovery_offset)
            and self.recovery_offset >= 0,
            "0 <= --recovery-parked-turn <= 1": 0 <= self.recovery_parked_turn <= 1,
            "--recovery-parked-jitter finite and >= 0 [m/s]": math.isfinite(
                self.recovery_parked_jitter
            )
            and self.recovery_parked_jitter >= 0,
            f"{', '.join(map(flag_of, LOSS_WEIGHTS))} finite and >= 0": all(
                math.isfinite(getattr(self, name)) and getattr(self, name) >= 0
                for name in LOSS_WEIGHTS
            ),
        }

    def recovery(self) -> RecoveryConfig:
        """The recovery windows of the training split (none when ``recovery_copies`` is 0)."""
        return RecoveryConfig(
            copies=self.recovery_copies,
            offset=self.recovery_offset,
            parked=self.recovery_parked,
            seed=self.seed,
            parked_turn=self.recovery_parked_turn,
            parked_jitter=self.recovery_parked_jitter,
        )

    def __post_init__(self) -> None:
        if isinstance(self.data, (str, os.PathLike)):  # one folder, e.g. from Python
            object.__setattr__(self, "data", (Path(self.data),))
        object.__setattr__(self, "data", tuple(Path(folder) for folder in self.data))
        object.__setattr__(self, "data_weights", tuple(map(float, self.data_weights)))
        check_field_types(self)
        counts = ("steps", "batch_size", "stride", "bucket", "eval_every", "log_every")
        check_at_least(
            self,
            {**dict.fromkeys((*counts, "num_samples"), 1), "threads": 0, "val_windows": 0},
            highs={"threads": MAX_THREADS, "steps": MAX_STEPS},
        )
        check_at_least(self, {"seed": 0}, highs={"seed": MAX_SEED})
        check_device(self.device)
        if self.model:
            model_config(self.model)  # a bad --model is refused before any data is read
        check_output_folder(self.out)
        broken = [rule for rule, holds in self.rules().items() if not holds]
        if broken:
            raise ValueError(f"riskflow-train needs {'; '.join(broken)}")


def _weights_rule(weights: tuple[float, ...], folders: int) -> str:
    """What ``--data-weights`` needs, said for the case at hand."""
    if weights and folders == 1:
        return "--data-weights only with several --data folders (one folder has every window)"
    if len(weights) != folders:
        return f"--data-weights: one weight per --data folder (got {len(weights)} for {folders})"
    return f"--data-weights finite and > 0 (got {list(weights)})"


def learning_rate(options: LoopOptions, step: int) -> float:
    """The learning rate of optimiser step ``step`` (0-based) under ``options.lr_schedule``.

    A pure function of the step, so a resumed run follows the uninterrupted schedule.
    ``cosine``: ``lr * min(1, (step + 1) / warmup) * (1 + cos(pi * step / steps)) / 2``.
    """
    if options.lr_schedule == "constant":
        return options.lr
    warmup = min(1.0, (step + 1) / options.warmup_steps) if options.warmup_steps else 1.0
    return options.lr * warmup * 0.5 * (1.0 + math.cos(math.pi * step / options.steps))


def model_config(text: str) -> ModelConfig:
    """``TrainOptions.model`` -> :class:`ModelConfig` (JSON text or a JSON file)."""
    if not text:
        return ModelConfig()
    try:
        fields = json.loads(Path(text).read_text() if text.endswith(".json") else text)
        if not isinstance(fields, dict):
            raise ValueError(f"expected a JSON object of ModelConfig fields, got {text!r:.60}")
        return ModelConfig.from_dict(fields)
    except (OSError, ValueError, TypeError) as error:  # a missing file, bad JSON, bad fields
        raise ValueError(f"--model: {error}") from None
