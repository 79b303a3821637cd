"""Validation of a generator on held-out windows: ADE/FDE, minADE over K samples, smoothness.

For every batch of windows (``docs/how-to/windows.md``, future fields included) :func:`evaluate`
measures, over every agent with at least one valid future step:

* ``ade`` / ``fde`` [m]: one-step samples (``sampler.sample`` with one ``eps`` per plan);
* ``min_ade`` / ``min_fde`` [m]: the best of ``num_samples`` plans per agent (drawn in
  one batched pass, ``sample(..., num_samples=K)``), as in trajectory forecasting;
* ``cv_ade`` / ``cv_fde`` [m]: the constant-velocity reference, zero actions rolled
  through the same dynamics from the same current states;
* ``jerk_rms`` / ``data_jerk_rms`` [m/s^3] and ``yaw_accel_rms`` / ``data_yaw_accel_rms``
  [rad/s^2]: root mean square of the step-to-step change of the sampled and the logged
  actions (smoothness; realism metrics penalise noisy plans);
* ``jerk_median`` / ``data_jerk_median`` [m/s^3]: the median absolute longitudinal jerk.
  The RMS is dominated by the data's rare large steps (a driver that brakes at once);
  the median shows the step-to-step noise of every plan, which the RMS hides (logged
  traffic holds its acceleration on most steps).

ADE of an agent is the mean distance over its valid future steps, FDE the distance at
its last valid step; both are averaged over agents. The noise comes from a generator
seeded with ``seed``, so the same model on the same windows gives the same numbers.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch import Tensor

from policies.learned.data import Normalizer
from policies.learned.generator import RiskFlowGenerator
from policies.learned.sampler import draw_noise, sample
from policies.learned.window_types import WindowBatch
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import DEFAULT_CONFIG, rollout
from riskflow_env.metrics.displacement import masked_displacement

METRICS = (
    "ade",
    "fde",
    "min_ade",
    "min_fde",
    "cv_ade",
    "cv_fde",
    "jerk_rms",
    "data_jerk_rms",
    "yaw_accel_rms",
    "data_yaw_accel_rms",
    "jerk_median",
    "data_jerk_median",
)


def displacement_errors(
    trajectories: Tensor, future: Tensor, future_valid: Tensor, agent_mask: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Per-agent ADE and FDE of predicted trajectories.

    Args:
        trajectories: ``(B, A, T, >=2)`` or, with a sample axis, ``(B, N, A, T, >=2)``
            predicted states (x, y [m], ...).
        future: ``(B, A, T, >=2)`` reference states.
        future_valid: ``(B, A, T)`` bool, reference observed.
        agent_mask: ``(B, A)`` bool, agent exists.

    Returns:
        ``ade, fde``: ``(B, A)`` or ``(B, N, A)`` [m] (0 where undefined); ``valid``:
        ``(B, A)`` bool, the agent exists and has a valid future step.
    """
    mask = future_valid.bool() & agent_mask.bool()[..., None]  # (B, A, T)
    valid = mask.any(dim=-1)
    if trajectories.dim() == future.dim() + 1:  # sample axis
        future, mask = future[:, None], mask[:, None]
    distance = (trajectories[..., :2] - future[..., :2]).norm(dim=-1)  # (B, [N,] A, T)
    ade, fde, _ = masked_displacement(distance, mask.expand(distance.shape))
    return ade, fde, valid


def _changes(actions: Tensor, valid: Tensor, dt: float) -> Tensor:
    """``(N, 2)``: ``diff(actions) / dt`` of both channels where both ends are valid."""
    change = (actions[..., 1:, :] - actions[..., :-1, :]) / dt
    return change[valid[..., 1:] & valid[..., :-1]]


@torch.no_grad()
def evaluate(
    model: RiskFlowGenerator,
    batches: Iterable[WindowBatch],
    normalizer: Normalizer,
    *,
    num_samples: int = 6,
    seed: int = 0,
    dynamics: DynamicsConfig = DEFAULT_CONFIG,
) -> dict[str, float]:
    """Validation metrics of ``model`` (see the module docstring) over ``batches``.

    Args:
        model: a one-call sampler (``encode``, ``average_velocity``, ``config``): the
            generator, or what an objective's ``sampler`` makes of it (EMA weights).
        batches: collated windows (``WindowBatch``) with the future fields, on the
            model's device.
        normalizer: action normalisation of the model.
        num_samples: ``K`` of minADE / minFDE.
        seed: seed of the noise.
        dynamics: time step and bounds of the rollouts.

    Returns:
        ``{name: value}`` for every name in :data:`METRICS`, plus ``agents`` (agents
        measured) and ``windows``.
    """
    sums = dict.fromkeys(("ade", "fde", "min_ade", "min_fde", "cv_ade", "cv_fde"), 0.0)
    counts = {"agents": 0.0, "windows": 0.0}
    changes: dict[str, list[Tensor]] = {"": [], "data_": []}
    generator: torch.Generator | None = None
    for batch in batches:
        scene = model.encode(batch)
        if generator is None:
            generator = torch.Generator(scene.context.device).manual_seed(seed)
        steps = model.config.future_steps
        eps = draw_noise(scene, steps, generator=generator)
        actions, trajectories = sample(model, scene, eps, normalizer, dynamics=dynamics)
        _, many = sample(
            model,
            scene,
            None,
            normalizer,
            num_samples=num_samples,
            generator=generator,
            dynamics=dynamics,
        )
        constant = rollout(scene.state, torch.zeros_like(actions), dynamics)
        truth = (batch.future, batch.future_valid, scene.agent_mask)
        ade, fde, valid = displacement_errors(trajectories, *truth)
        min_ade, min_fde, _ = displacement_errors(many, *truth)
        cv_ade, cv_fde, _ = displacement_errors(constant, *truth)
        weight = valid.to(ade.dtype)
        for name, value in (
            ("ade", ade),
            ("fde", fde),
            ("min_ade", min_ade.min(dim=1).values),
            ("min_fde", min_fde.min(dim=1).values),
            ("cv_ade", cv_ade),
            ("cv_fde", cv_fde),
        ):
            sums[name] += float((value * weight).sum())
        counts["agents"] += float(weight.sum())
        counts["windows"] += batch.batch_size
        plan_valid = scene.agent_mask[..., None].expand(actions.shape[:-1])
        data_valid = batch.actions_valid.bool() & plan_valid
        changes[""].append(_changes(actions, plan_valid, dynamics.dt))
        changes["data_"].append(_changes(batch.actions, data_valid, dynamics.dt))
    if counts["agents"] == 0:
        raise ValueError("evaluate: no agent with a valid future in the batches")
    metrics = {name: total / counts["agents"] for name, total in sums.items()}
    for prefix, parts in changes.items():
        change = torch.cat(parts).double()  # (N, 2): jerk, yaw acceleration
        if not len(change):
            change = torch.zeros(1, 2, dtype=torch.float64)
        rms = change.square().mean(dim=0).sqrt()
        metrics[f"{prefix}jerk_rms"] = float(rms[0])
        metrics[f"{prefix}yaw_accel_rms"] = float(rms[1])
        metrics[f"{prefix}jerk_median"] = float(change[:, 0].abs().median())
    metrics["agents"] = counts["agents"]
    metrics["windows"] = counts["windows"]
    return metrics
