"""The training loop every generator kind shares; the objective is an argument.

:func:`fit` runs ``options.steps`` optimiser steps on batches of windows
(``docs/WINDOWS.md``): the :class:`Objective`'s loss (MeanFlow's in
``policies.riskflow.meanflow``, the DDPM's in ``policies.baselines.diffusion.train``),
Adam, gradient-norm clipping and the EMA of the weights (``ema.EMA``), which is what is
validated and saved. Validation (``validation.evaluate``) samples the objective's
``sampler(ema_model)`` every ``--eval-every`` steps on a fixed subset of the validation
windows. Use one thread per process on a small shared machine (two threads on two busy
cores made a step 20x slower); on an otherwise idle 2-core machine ``--threads 2`` makes
a step 1.5x faster (0.33 against 0.50 s on the shipped recipe's mixed batches,
2026-11-27).

``OUT/checkpoint.pt`` is the resumable state (``--resume`` continues from it: model,
EMA, optimiser, step and random state, so the result equals an uninterrupted run on
the CPU); ``OUT/generator.pt`` is the same without the training state, the file to
ship; ``OUT/metrics.jsonl`` logs training and validation metrics. Windows are cached
in ``DATA/cache/`` and the action statistics in ``DATA/norm_stats.json``; for the shipped
bank (or a read-only ``DATA``) both go to the user cache (``policies.learned.data_cache``).
``riskflow-train`` (:mod:`policies.train`) is the command line over it.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from policies.learned.batches import batch_order, collated, load_splits
from policies.learned.checkpoint import (
    build_checkpoint,
    checkpoint_kind,
    load_checkpoint,
    normalizer_of,
)
from policies.learned.checkpoint import save_checkpoint as write
from policies.learned.config import ModelConfig
from policies.learned.data import ActionNormalizer, compute_action_stats
from policies.learned.data import load_or_compute_stats as action_stats
from policies.learned.ema import EMA
from policies.learned.generator import RiskFlowGenerator
from policies.learned.recovery import RecoveryConfig
from policies.learned.validation import evaluate
from policies.learned.window_types import WindowBatch
from riskflow_env.scenarios.folders import scene_files

CHECKPOINT, GENERATOR, METRICS_LOG = "checkpoint.pt", "generator.pt", "metrics.jsonl"
LR_SCHEDULES = ("constant", "cosine")
# torch.func.jvp's first call warns that torch.jit.script is deprecated (torch's own use).
warnings.filterwarnings("ignore", message=r".*torch\.jit\.script.*", category=DeprecationWarning)


class Objective(Protocol):
    """What a generator kind plugs into :func:`fit`."""

    kind: str
    """the generator kind written to the checkpoint (``"meanflow"``, ``"diffusion"``)"""

    def loss(
        self,
        model: RiskFlowGenerator,
        batch: WindowBatch,
        normalizer: ActionNormalizer,
        eps: Tensor,
        generator: torch.Generator,
        **weights: float,
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """One step's loss and metrics from the noise ``eps`` (the batch's action shape);
        further draws (times, levels) come from ``generator``."""
        ...

    def sampler(self, model: RiskFlowGenerator) -> Any:
        """``model`` as the one-call sampler that validation draws plans from."""
        ...


@dataclass(frozen=True)
class LoopOptions:
    """Options of the training loop (``riskflow-train`` adds the generator's)."""

    data: tuple[Path, ...]
    """training scenes: a folder written by `riskflow-data generate`, or a ScenarioNet dataset
    folder (dataset_summary.pkl; scenes read one at a time when the windows are cut); several
    folders train on all their scenes together (then --val-data is needed)"""
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
    recovery_kerbside: int = 0
    """cars parked at the kerb, on the road, added to each recovery window (learned.parked)"""
    time_budget_min: float = 0.0
    """stop cleanly and save after this many minutes of this run (0: no limit)"""

    def rules(self) -> dict[str, bool]:
        """``{rule: holds}`` of the option checks (subclasses add theirs)."""
        counts = (self.steps, self.batch_size, self.stride, self.bucket, self.eval_every)
        return {
            "--steps, --batch-size, --stride, --bucket, --eval-every, --log-every, "
            "--num-samples >= 1": min(*counts, self.log_every, self.num_samples) >= 1,
            "--lr > 0": self.lr > 0,
            f"--lr-schedule in {LR_SCHEDULES}": self.lr_schedule in LR_SCHEDULES,
            "0 <= --warmup-steps < --steps": 0 <= self.warmup_steps < self.steps,
            "--grad-clip > 0": self.grad_clip > 0,
            "0 <= --ema-decay < 1": 0 <= self.ema_decay < 1,
            "0 < --val-fraction < 1": 0 < self.val_fraction < 1,
            "--data: one folder, or several with --val-data": len(self.data) == 1
            or (len(self.data) > 1 and self.val_data is not None),
            "--recovery-copies, --recovery-parked, --recovery-kerbside >= 0": min(
                self.recovery_copies, self.recovery_parked, self.recovery_kerbside
            )
            >= 0,
            "--recovery-offset >= 0": math.isfinite(self.recovery_offset)
            and self.recovery_offset >= 0,
        }

    def recovery(self) -> RecoveryConfig:
        """The recovery windows of the training split (none when ``recovery_copies`` is 0)."""
        return RecoveryConfig(
            copies=self.recovery_copies,
            offset=self.recovery_offset,
            parked=self.recovery_parked,
            kerbside=self.recovery_kerbside,
            seed=self.seed,
        )

    def __post_init__(self) -> None:
        if isinstance(self.data, (str, os.PathLike)):  # one folder, e.g. from Python
            object.__setattr__(self, "data", (Path(self.data),))
        object.__setattr__(self, "data", tuple(Path(folder) for folder in self.data))
        broken = [rule for rule, holds in self.rules().items() if not holds]
        if broken:
            raise ValueError(f"riskflow-train needs {'; '.join(broken)}")


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
    return ModelConfig.from_dict(
        json.loads(Path(text).read_text() if text.endswith(".json") else text)
    )


def _plain(options: LoopOptions) -> dict[str, Any]:
    def plain(value: Any) -> Any:
        if isinstance(value, tuple):
            return [plain(item) for item in value]
        return str(value) if isinstance(value, Path) else value

    return {key: plain(value) for key, value in vars(options).items()}


def _rng_state(noise: torch.Generator) -> dict[str, Any]:
    _, key, position, has_gauss, gauss = np.random.get_state()  # noqa: NPY002
    numpy = {"key": torch.from_numpy(key.astype(np.int64)), "pos": int(position)}
    numpy |= {"has_gauss": int(has_gauss), "gauss": float(gauss)}
    return {"noise": noise.get_state(), "torch": torch.get_rng_state(), "numpy": numpy}


def _set_rng_state(noise: torch.Generator, state: dict[str, Any]) -> None:
    noise.set_state(state["noise"].cpu())
    torch.set_rng_state(state["torch"].cpu())
    numpy = state["numpy"]
    key = numpy["key"].cpu().numpy().astype(np.uint32)
    np.random.set_state(("MT19937", key, numpy["pos"], numpy["has_gauss"], numpy["gauss"]))  # noqa: NPY002


def _initial(
    options: LoopOptions, objective: Objective
) -> tuple[RiskFlowGenerator, ActionNormalizer]:
    """``--init``'s model and action statistics (SystemExit naming what does not fit)."""
    try:
        state = load_checkpoint(options.init)
        expected = model_config(options.model) if options.model else None
        model = RiskFlowGenerator.from_checkpoint(state, expected)
        normalizer = normalizer_of(state)
    except (OSError, ValueError) as err:  # missing file, CheckpointError (a ValueError)
        raise SystemExit(f"riskflow-train: --init: {err}") from None
    if checkpoint_kind(state) != objective.kind:
        raise SystemExit(
            f"riskflow-train: --init: {options.init} holds a {checkpoint_kind(state)} "
            f"generator, not {objective.kind}"
        )
    return model, normalizer


def fit(options: LoopOptions, objective: Objective) -> dict[str, Any]:
    """Train with ``objective`` (or, with ``options.resume``, continue); returns the last
    metrics logged."""
    torch.manual_seed(options.seed)
    np.random.seed(options.seed)  # noqa: NPY002 (not used by training; seeded for callers)
    if options.threads > 0:
        torch.set_num_threads(options.threads)
    device, out = options.device, Path(options.out)
    if options.resume and not (out / CHECKPOINT).is_file():
        raise SystemExit(f"riskflow-train: --resume: no checkpoint at {out / CHECKPOINT}")
    start = None if options.resume or options.init is None else _initial(options, objective)
    folders = [("--data", folder) for folder in options.data] + [("--val-data", options.val_data)]
    for flag, folder in folders:
        try:
            if folder is not None:
                scene_files(folder)
        except (OSError, ValueError) as err:  # missing, a file, no scenes, a bad index
            raise SystemExit(f"riskflow-train: {flag}: {err}") from None
    try:
        splits = (options.data, options.val_data, options.val_fraction, options.stride)
        train_set, val_set = load_splits(*splits, recovery=options.recovery())
    except ValueError as err:
        raise SystemExit(f"riskflow-train: {err}") from None
    state = load_checkpoint(out / CHECKPOINT, device) if options.resume else {}
    if start is not None:
        config = start[0].config
    elif options.resume and not options.model:  # e.g. a fine-tune's, from its --init
        config = ModelConfig.from_dict(state["config"])
    else:
        config = model_config(options.model)
    model = RiskFlowGenerator(config).to(device)
    if start is not None:
        model.load_state_dict(start[0].state_dict())
    ema = EMA(model, options.ema_decay)
    optimizer = torch.optim.Adam(model.parameters(), lr=options.lr)
    noise = torch.Generator(device).manual_seed(options.seed)  # eps and (t, r)
    step, elapsed, metrics = 0, 0.0, {}
    if options.resume:
        if "training" not in state:
            raise SystemExit(f"riskflow-train: {out / CHECKPOINT} holds no training state")
        trained = state.get("train_config", {}).get("generator", "meanflow")
        if trained != objective.kind:
            raise SystemExit(f"riskflow-train: --resume: {out} trained --generator {trained}")
        ema.model.load_state_dict(RiskFlowGenerator.from_checkpoint(state, config).state_dict())
        model.load_checkpoint_state(state["training"]["raw_state_dict"])
        optimizer.load_state_dict(state["training"]["optimizer"])
        _set_rng_state(noise, state["training"]["rng"])
        normalizer: ActionNormalizer = normalizer_of(state)
        step, elapsed, metrics = state["step"], state["training"]["elapsed_s"], state["metrics"]
    elif start is not None:
        normalizer = start[1]
    else:
        normalizer = (  # cached beside one folder's scenes; several: computed (fast)
            action_stats(options.data[0], train_set)
            if len(options.data) == 1
            else compute_action_stats(train_set)
        )
    agents = train_set.agent_counts()
    per_epoch = len(agents) // options.batch_size
    if per_epoch == 0:
        raise SystemExit(f"riskflow-train: {len(agents)} training windows < --batch-size")
    val_indices = np.arange(len(val_set))
    if 0 < options.val_windows < len(val_set):
        val_indices = np.sort(
            np.random.default_rng(0).choice(val_indices, options.val_windows, False)
        )
    weights = {
        name: getattr(options, name)
        for name in ("heading_weight", "action_weight", "collision_weight", "offroad_weight")
    }

    def validate() -> dict[str, float]:
        batches = (
            collated(val_set, val_indices[i : i + options.batch_size], device)
            for i in range(0, len(val_indices), options.batch_size)
        )
        result = evaluate(
            objective.sampler(ema.model), batches, normalizer,
            num_samples=options.num_samples, seed=options.seed,
        )  # fmt: skip
        return {f"val_{k}": v for k, v in result.items()}

    def save() -> None:
        training = {
            "raw_state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
            "optimizer": optimizer.state_dict(),
            "rng": _rng_state(noise),
            "elapsed_s": elapsed,
        }
        config = _plain(options) | {"generator": objective.kind}
        common = {"step": step, "train_config": config, "metrics": metrics}
        write(
            build_checkpoint(ema.model, normalizer, training=training, **common), out / CHECKPOINT
        )
        write(build_checkpoint(ema.model, normalizer, **common), out / GENERATOR)

    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    budget = 60.0 * options.time_budget_min if options.time_budget_min > 0 else math.inf
    interval = 0.5 if sys.stderr.isatty() else 30.0  # [s]: a log file gets few lines
    bar = tqdm(
        total=options.steps, desc="riskflow-train", initial=step, unit="step", mininterval=interval
    )
    sums: dict[str, list[float]] = {}
    epoch, batches = -1, np.zeros((0, options.batch_size), dtype=np.int64)
    with (out / METRICS_LOG).open("a") as log:
        while step < options.steps:
            tick = time.perf_counter()
            if step // per_epoch != epoch:
                epoch = step // per_epoch
                batches = batch_order(
                    agents, options.batch_size, options.bucket, options.seed, epoch
                )
            batch = collated(train_set, batches[step % per_epoch], device)
            eps = torch.randn(batch.actions.shape, generator=noise, device=device)
            loss, values = objective.loss(model, batch, normalizer, eps, noise, **weights)
            values["lr"] = learning_rate(options, step)
            for group in optimizer.param_groups:
                group["lr"] = values["lr"]
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            values["grad_norm"] = torch.nn.utils.clip_grad_norm_(
                model.parameters(), options.grad_clip
            )
            optimizer.step()
            ema.update(model)
            step += 1
            seconds = time.perf_counter() - tick
            elapsed += seconds
            values["samples_per_s"] = options.batch_size / seconds
            for key, value in values.items():
                sums.setdefault(key, []).append(float(value))
            bar.update()
            bar.set_postfix(
                loss=f"{float(values['loss']):.3f}", samples_s=f"{values['samples_per_s']:.1f}"
            )
            over_budget = time.perf_counter() - started > budget
            done = step >= options.steps or over_budget
            logged = step % options.log_every == 0 or step % options.eval_every == 0 or done
            if logged:
                metrics = {f"train_{k}": sum(v) / len(v) for k, v in sums.items()}
                metrics |= {"step": step, "epoch": epoch, "elapsed_s": elapsed}
                sums = {}
            if step % options.eval_every == 0 or done:
                metrics |= validate()
                bar.write(json.dumps({k: round(v, 4) for k, v in metrics.items()}))
                save()
            if logged:
                log.write(json.dumps(metrics) + "\n")
                log.flush()
            if over_budget:
                bar.write(f"riskflow-train: time budget reached at step {step}; saved")
                break
    bar.close()
    return metrics
