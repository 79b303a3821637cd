"""``riskflow-train``: train the RiskFlow generator on a scenario bank.

::

    riskflow-data generate --out data/train --scenes 626 --split train --seed 0
    riskflow-data generate --out data/val --scenes 140 --split eval --seed 1
    riskflow-train --data data/train --val-data data/val --out runs/riskflow --lr 5e-4

One step: a batch of windows (``docs/WINDOWS.md``), noise ``eps`` and times ``(t, r)``
(``TimeSampler``: logit-normal, ``r = t`` for 20 %; always with ``--flow-matching``),
the MeanFlow objective (``meanflow.meanflow_loss``; ``flow_matching_loss`` for the
reference), Adam, gradient-norm clipping, and the EMA of the weights (``ema.EMA``),
which is what is validated and saved. The loss is the trajectory-space error plus
``action_weight`` (default 1) times the normalised action error: positions barely see
high-frequency action noise, so without it one-step plans keep the noise of ``eps``
(pilot: jerk 16 m/s^3 against 4.6 with it, the data's 7.2; ADE 1.58 against 1.51 m).
Use one thread per process on a small shared machine (two threads on two busy cores
made a step 20x slower). Validation (``evaluate.evaluate``) runs every
``--eval-every`` steps on a fixed subset of the validation windows.

``OUT/checkpoint.pt`` is the resumable state (``--resume`` continues from it: model,
EMA, optimiser, step and random state, so the result equals an uninterrupted run on
the CPU); ``OUT/generator.pt`` is the same without the training state, the file to
ship; ``OUT/metrics.jsonl`` logs training and validation metrics. Windows are cached
in ``DATA/cache/`` and the action statistics in ``DATA/norm_stats.json``; for the shipped
bank (or a read-only ``DATA``) both go to the user cache (``policies.riskflow.data_cache``).

``--generator diffusion`` trains the DDPM denoiser of the CTG / CTG++ / CCDiff-style
baselines in this same loop (same network, data, EMA and validation; objective and
sampler from ``policies.baselines.diffusion.train``; docs/BASELINES.md).
"""

from __future__ import annotations

import json
import math
import sys
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from policies.riskflow.batches import batch_order, collated, load_splits
from policies.riskflow.checkpoint import build_checkpoint, load_checkpoint, normalizer_of
from policies.riskflow.checkpoint import save_checkpoint as write
from policies.riskflow.config import ModelConfig
from policies.riskflow.data import ActionNormalizer
from policies.riskflow.data import load_or_compute_stats as action_stats
from policies.riskflow.dataclass_cli import parse_dataclass
from policies.riskflow.ema import EMA
from policies.riskflow.evaluate import evaluate
from policies.riskflow.generator import RiskFlowGenerator
from policies.riskflow.meanflow import flow_matching_loss, meanflow_loss
from policies.riskflow.time_sampler import TimeSampler
from riskflow_env.scenarios.io import require_scenarios

CHECKPOINT, GENERATOR, METRICS_LOG = "checkpoint.pt", "generator.pt", "metrics.jsonl"
GENERATORS = ("meanflow", "diffusion")
# torch.func.jvp's first call warns that torch.jit.script is deprecated (torch's own use).
warnings.filterwarnings("ignore", message=r".*torch\.jit\.script.*", category=DeprecationWarning)


@dataclass(frozen=True)
class TrainOptions:
    """Options of ``riskflow-train``."""

    data: Path
    """scenario directory written by `riskflow-data generate` (training scenes)"""
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
    """Adam learning rate"""
    ema_decay: float = 0.995
    """EMA decay of the weights per step"""
    grad_clip: float = 1.0
    """maximum global gradient norm (inf: no clipping)"""
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
    time_budget_min: float = 0.0
    """stop cleanly and save after this many minutes of this run (0: no limit)"""

    def __post_init__(self) -> None:
        counts = (self.steps, self.batch_size, self.stride, self.bucket, self.eval_every)
        rules = {
            "--steps, --batch-size, --stride, --bucket, --eval-every, --log-every, "
            "--num-samples >= 1": min(*counts, self.log_every, self.num_samples) >= 1,
            "--lr > 0": self.lr > 0,
            "--grad-clip > 0": self.grad_clip > 0,
            "0 <= --ema-decay < 1": 0 <= self.ema_decay < 1,
            "0 < --val-fraction < 1": 0 < self.val_fraction < 1,
            f"--generator in {GENERATORS}": self.generator in GENERATORS,
            "--flow-matching only with --generator meanflow": not (
                self.flow_matching and self.generator != "meanflow"
            ),
            "--diffusion-steps, --val-sampling-steps >= 1": min(
                self.diffusion_steps, self.val_sampling_steps
            )
            >= 1,
        }
        broken = [rule for rule, holds in rules.items() if not holds]
        if broken:
            raise ValueError(f"riskflow-train needs {'; '.join(broken)}")


def model_config(text: str) -> ModelConfig:
    """``TrainOptions.model`` -> :class:`ModelConfig` (JSON text or a JSON file)."""
    if not text:
        return ModelConfig()
    return ModelConfig.from_dict(
        json.loads(Path(text).read_text() if text.endswith(".json") else text)
    )


def _plain(options: TrainOptions) -> dict[str, Any]:
    return {k: str(v) if isinstance(v, Path) else v for k, v in vars(options).items()}


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


def train(options: TrainOptions) -> dict[str, Any]:
    """Train (or, with ``options.resume``, continue); returns the last metrics logged."""
    torch.manual_seed(options.seed)
    np.random.seed(options.seed)  # noqa: NPY002 (not used by training; seeded for callers)
    if options.threads > 0:
        torch.set_num_threads(options.threads)
    device, out = options.device, Path(options.out)
    if options.resume and not (out / CHECKPOINT).is_file():
        raise SystemExit(f"riskflow-train: --resume: no checkpoint at {out / CHECKPOINT}")
    for flag, folder in (("--data", options.data), ("--val-data", options.val_data)):
        try:
            if folder is not None:
                require_scenarios(folder)
        except OSError as err:  # missing, a file, no scene files
            raise SystemExit(f"riskflow-train: {flag}: {err}") from None
    try:
        splits = (options.data, options.val_data, options.val_fraction, options.stride)
        train_set, val_set = load_splits(*splits)
    except ValueError as err:
        raise SystemExit(f"riskflow-train: {err}") from None
    config = model_config(options.model)
    model = RiskFlowGenerator(config).to(device)
    objective = None
    if options.generator == "diffusion":
        from policies.baselines.diffusion.train import DiffusionObjective

        objective = DiffusionObjective.from_options(options)
    ema = EMA(model, options.ema_decay)
    optimizer = torch.optim.Adam(model.parameters(), lr=options.lr)
    noise = torch.Generator(device).manual_seed(options.seed)  # eps and (t, r)
    step, elapsed, metrics = 0, 0.0, {}
    if options.resume:
        state = load_checkpoint(out / CHECKPOINT, device)
        if "training" not in state:
            raise SystemExit(f"riskflow-train: {out / CHECKPOINT} holds no training state")
        trained = state.get("train_config", {}).get("generator", "meanflow")
        if trained != options.generator:
            raise SystemExit(f"riskflow-train: --resume: {out} trained --generator {trained}")
        ema.model.load_state_dict(RiskFlowGenerator.from_checkpoint(state, config).state_dict())
        model.load_checkpoint_state(state["training"]["raw_state_dict"])
        optimizer.load_state_dict(state["training"]["optimizer"])
        _set_rng_state(noise, state["training"]["rng"])
        normalizer: ActionNormalizer = normalizer_of(state)
        step, elapsed, metrics = state["step"], state["training"]["elapsed_s"], state["metrics"]
    else:
        normalizer = action_stats(options.data, train_set)
    agents = np.array([train_set.window(i)["agent_mask"].shape[0] for i in range(len(train_set))])
    per_epoch = len(agents) // options.batch_size
    if per_epoch == 0:
        raise SystemExit(f"riskflow-train: {len(agents)} training windows < --batch-size")
    val_indices = np.arange(len(val_set))
    if 0 < options.val_windows < len(val_set):
        val_indices = np.sort(
            np.random.default_rng(0).choice(val_indices, options.val_windows, False)
        )
    sampler = TimeSampler(
        equal_fraction=options.equal_fraction, flow_matching=options.flow_matching
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
        sampler_model = ema.model if objective is None else objective.sampler(ema.model)
        result = evaluate(
            sampler_model, batches, normalizer, num_samples=options.num_samples,
            seed=options.seed, flow_matching=options.flow_matching,
        )  # fmt: skip
        return {f"val_{k}": v for k, v in result.items()}

    def save() -> None:
        training = {
            "raw_state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
            "optimizer": optimizer.state_dict(),
            "rng": _rng_state(noise),
            "elapsed_s": elapsed,
        }
        common = {"step": step, "train_config": _plain(options), "metrics": metrics}
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
            if objective is not None:
                loss, values = objective.loss(model, batch, normalizer, noise, **weights)
            else:
                eps = torch.randn(batch["actions"].shape, generator=noise, device=device)
                t, r = sampler(options.batch_size, generator=noise, device=device)
                if options.flow_matching:
                    loss, values = flow_matching_loss(model, batch, normalizer, eps, t, **weights)
                else:
                    loss, values = meanflow_loss(model, batch, normalizer, eps, t, r, **weights)
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


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``riskflow-train`` console script."""
    train(parse_dataclass(TrainOptions, argv, "riskflow-train", __doc__.split("\n")[0]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
