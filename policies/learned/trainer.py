"""The training loop every generator kind shares; the objective is an argument.

:func:`fit` runs ``options.steps`` optimiser steps on batches of windows
(``docs/how-to/windows.md``): the :class:`Objective`'s loss (MeanFlow's in
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
``riskflow-train`` (:mod:`policies.train`) is the command line over it. Started by
``torchrun``, it trains on every process, each on its share of every batch, and only rank 0
validates and writes (:mod:`policies.learned.distributed`).
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from policies.learned.adversary_config import default_window_config
from policies.learned.batches import FolderShares, batch_order, collated, load_splits
from policies.learned.checkpoint import (
    build_checkpoint,
    checkpoint_kind,
    load_checkpoint,
    normalizer_of,
)
from policies.learned.checkpoint import save_checkpoint as write
from policies.learned.config import ModelConfig
from policies.learned.data import ActionNormalizer
from policies.learned.distributed import (
    Ranks,
    Shard,
    any_process,
    average_gradients,
    average_values,
    broadcast_parameters,
    global_means,
    main_first,
    process_device,
    process_group,
)
from policies.learned.ema import EMA
from policies.learned.generator import RiskFlowGenerator
from policies.learned.run_state import (
    check_resume,
    initial_normalizer,
    plain_options,
    rng_state,
    set_rng_state,
)
from policies.learned.train_options import LoopOptions, learning_rate, model_config
from policies.learned.trajectory_loss import LossWeights
from policies.learned.validation import evaluate
from policies.learned.window_types import WindowBatch
from riskflow_env.atomic_files import write_text
from riskflow_env.scenarios.folders import scene_files

CHECKPOINT, GENERATOR, METRICS_LOG = "checkpoint.pt", "generator.pt", "metrics.jsonl"
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
        weights: LossWeights,
        shard: Shard,
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """One step's loss and metrics from the noise ``eps`` (the batch's action shape);
        further draws (times, levels) come from ``generator``, one per window of the
        global batch, of which ``batch`` holds the rows ``shard`` (all on one process)."""
        ...

    def sampler(self, model: RiskFlowGenerator) -> Any:
        """``model`` as the one-call sampler that validation draws plans from."""
        ...


def _initial(
    options: LoopOptions, objective: Objective
) -> tuple[RiskFlowGenerator, ActionNormalizer]:
    """``--init``'s model and action statistics (ValueError naming what does not fit)."""
    try:
        state = load_checkpoint(options.init)
        expected = model_config(options.model) if options.model else None
        model = RiskFlowGenerator.from_checkpoint(state, expected)
        normalizer = normalizer_of(state)
    except (OSError, ValueError) as err:  # missing file, CheckpointError (a ValueError)
        raise ValueError(f"--init: {err}") from None
    if checkpoint_kind(state) != objective.kind:
        raise ValueError(
            f"--init: {options.init} holds a {checkpoint_kind(state)} "
            f"generator, not {objective.kind}"
        )
    return model, normalizer


class TrainingDiverged(ValueError):
    """The loss or its gradient became NaN or inf: training stops before the step that
    would write them into the weights."""


def _drop_rows_after(path: Path, step: int) -> None:
    """Drop the rows of the metrics log after the checkpoint's ``step`` (logged by the run
    that was interrupted; the resumed run logs those steps again)."""
    if not path.is_file():
        return
    lines = path.read_text().splitlines(keepends=True)

    def before(line: str) -> bool:
        try:
            return json.loads(line)["step"] <= step
        except (ValueError, KeyError, TypeError):  # a line torn by a kill
            return False

    kept = [line for line in lines if before(line)]
    if len(kept) < len(lines):
        write_text(path, "".join(kept))


def fit(options: LoopOptions, objective: Objective) -> dict[str, Any]:
    """Train with ``objective`` (or, with ``options.resume``, continue); returns the last
    metrics logged (on every process of a ``torchrun`` launch: ``distributed``)."""
    with process_group(options.device) as ranks:
        return _fit(options, objective, ranks)


def _fit(options: LoopOptions, objective: Objective, ranks: Ranks) -> dict[str, Any]:
    device = process_device(options.device, ranks)
    if options.batch_size < ranks.world:
        raise ValueError(f"--batch-size {options.batch_size} < {ranks.world} processes")
    torch.manual_seed(options.seed)
    np.random.seed(options.seed)  # noqa: NPY002 (not used by training; seeded for callers)
    if options.threads > 0:
        torch.set_num_threads(options.threads)
    out = Path(options.out)
    if options.resume and not (out / CHECKPOINT).is_file():
        raise ValueError(f"--resume: no checkpoint at {out / CHECKPOINT}")
    if not options.resume and (out / CHECKPOINT).is_file():
        raise ValueError(
            f"--out {out} holds a training run already ({CHECKPOINT}): continue it with "
            "--resume, or choose another --out"
        )
    start = None if options.resume or options.init is None else _initial(options, objective)
    folders = [("--data", folder) for folder in options.data] + [("--val-data", options.val_data)]
    for flag, folder in folders:
        try:
            if folder is not None:
                scene_files(folder)
        except (OSError, ValueError) as err:  # missing, a file, no scenes, a bad index
            raise ValueError(f"{flag}: {err}") from None
    state = load_checkpoint(out / CHECKPOINT, device) if options.resume else {}
    if start is not None:
        config = start[0].config
    elif options.resume and not options.model:  # e.g. a fine-tune's, from its --init
        config = ModelConfig.from_dict(state["config"])
    else:
        config = model_config(options.model)
    splits = (options.data, options.val_data, options.val_fraction, options.stride)
    window = default_window_config(config)  # the crops the model reads
    with main_first(ranks):  # rank 0 writes the window caches, the others read them
        train_set, val_set = load_splits(*splits, recovery=options.recovery(), window=window)
        normalizer = initial_normalizer(options, state, start, train_set)
    weights = options.data_weights  # (): every folder its share of the windows
    shares = FolderShares.of(train_set, options.data, weights) if weights else None
    model = RiskFlowGenerator(config).to(device)
    if start is not None:
        model.load_state_dict(start[0].state_dict())
    ema = EMA(model, options.ema_decay)
    optimizer = torch.optim.Adam(model.parameters(), lr=options.lr)
    noise = torch.Generator(device).manual_seed(options.seed)  # eps and (t, r)
    step, elapsed, metrics = 0, 0.0, {}
    if options.resume:
        if "training" not in state:
            raise ValueError(f"{out / CHECKPOINT} holds no training state")
        trained = state.get("train_config", {}).get("generator", "meanflow")
        if trained != objective.kind:
            raise ValueError(f"--resume: {out} trained --generator {trained}")
        ema.model.load_state_dict(RiskFlowGenerator.from_checkpoint(state, config).state_dict())
        model.load_checkpoint_state(state["training"]["raw_state_dict"])
        optimizer.load_state_dict(state["training"]["optimizer"])
        set_rng_state(noise, state["training"]["rng"])
        step, elapsed, metrics = state["step"], state["training"]["elapsed_s"], state["metrics"]
        check_resume(options, state.get("train_config", {}), objective.kind)
        if ranks.main:
            _drop_rows_after(out / METRICS_LOG, step)
    broadcast_parameters(model, ranks)  # the same start everywhere, whatever the machine
    agents = train_set.agent_counts()
    per_epoch = len(agents) // options.batch_size
    if per_epoch == 0:
        raise ValueError(f"{len(agents)} training windows < --batch-size")
    val_indices = np.arange(len(val_set))
    if 0 < options.val_windows < len(val_set):
        val_indices = np.sort(
            np.random.default_rng(0).choice(val_indices, options.val_windows, False)
        )
    weights = LossWeights.from_options(options)

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
            "rng": rng_state(noise),
            "elapsed_s": elapsed,
        }
        config = plain_options(options) | {"generator": objective.kind}
        if ranks.world > 1:
            config["processes"] = ranks.world
        common = {"step": step, "train_config": config, "metrics": metrics}
        write(
            build_checkpoint(ema.model, normalizer, training=training, **common), out / CHECKPOINT
        )
        write(build_checkpoint(ema.model, normalizer, **common), out / GENERATOR)

    if ranks.main:
        out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    budget = 60.0 * options.time_budget_min if options.time_budget_min > 0 else math.inf
    end = options.stop_step or options.steps  # --stop-step: early, on --steps' schedule
    if step >= end and ranks.main:
        flag = "--stop-step" if options.stop_step else "--steps"
        print(
            f"riskflow-train: {out / CHECKPOINT} is at step {step}, {flag} is {end}: nothing "
            f"left to train (raise {flag} to go on)",
            file=sys.stderr,
        )
    first = step
    interval = 0.5 if sys.stderr.isatty() else 30.0  # [s]: a log file gets few lines
    bar = tqdm(
        total=end, desc="riskflow-train", initial=step, unit="step", mininterval=interval,
        disable=not ranks.main,
    )  # fmt: skip
    sums: dict[str, list[float]] = {}
    epoch, batches = -1, np.zeros((0, options.batch_size), dtype=np.int64)
    log_file = (out / METRICS_LOG).open("a") if ranks.main else open(os.devnull, "w")
    with bar, log_file as log:  # the bar closes before an interrupt's message is printed
        while step < end:
            tick = time.perf_counter()
            if step // per_epoch != epoch:
                epoch = step // per_epoch
                batches = batch_order(
                    agents, options.batch_size, options.bucket, options.seed, epoch, shares
                )
            rows = batches[step % per_epoch]  # the global batch; this process's shard
            shard = ranks.shard(len(rows))
            batch = collated(train_set, shard.rows(rows), device)
            shape = (len(rows), int(agents[rows].max()), *batch.actions.shape[2:])
            eps = torch.randn(shape, generator=noise, device=device)  # the global batch's
            eps = shard.rows(eps)[:, : batch.actions.shape[1]]
            with global_means(ranks):
                loss, values = objective.loss(model, batch, normalizer, eps, noise, weights, shard)
            values["lr"] = learning_rate(options, step)
            for group in optimizer.param_groups:
                group["lr"] = values["lr"]
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            average_gradients(model.parameters(), ranks)
            values["grad_norm"] = torch.nn.utils.clip_grad_norm_(
                model.parameters(), options.grad_clip
            )
            diverged = not (torch.isfinite(loss) and torch.isfinite(values["grad_norm"]))
            if any_process(bool(diverged), ranks):  # before the step spoils the weights
                raise TrainingDiverged(
                    f"the loss or its gradient is not finite at step {step + 1} (lr "
                    f"{values['lr']:.3g}): lower --lr or check the data; the weights of the "
                    f"last save in {out} are kept"
                )
            optimizer.step()
            ema.update(model)
            step += 1
            seconds = time.perf_counter() - tick
            elapsed += seconds
            values["samples_per_s"] = options.batch_size / seconds
            for key, value in average_values(values, ranks).items():
                sums.setdefault(key, []).append(value)
            bar.update()
            bar.set_postfix(  # shown at the bar's next refresh (mininterval), not now
                loss=f"{float(values['loss']):.3f}",
                samples_s=f"{values['samples_per_s']:.1f}",
                refresh=False,
            )
            over_budget = any_process(time.perf_counter() - started > budget, ranks)
            done = step >= end or over_budget
            logged = step % options.log_every == 0 or step % options.eval_every == 0 or done
            if logged:
                metrics = {f"train_{k}": sum(v) / len(v) for k, v in sums.items()}
                metrics |= {"step": step, "epoch": epoch, "elapsed_s": elapsed}
                sums = {}
            if ranks.main and (step % options.eval_every == 0 or done):
                metrics |= validate()
                bar.write(json.dumps({k: round(v, 4) for k, v in metrics.items()}))
                save()
            if logged:
                log.write(json.dumps(metrics) + "\n")
                log.flush()
            if over_budget:
                if ranks.main:
                    bar.write(f"riskflow-train: time budget reached at step {step}; saved")
                break
    if ranks.main and step > first:  # steps were trained, and saved
        print(
            f"riskflow-train: wrote {out / GENERATOR} (to plan with), {out / CHECKPOINT} "
            f"(--resume) and {out / METRICS_LOG}",
            file=sys.stderr,
        )
    return metrics
