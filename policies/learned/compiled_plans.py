"""The compiled planning loops: the avoidance steps
(:func:`policies.learned.plan_avoidance.avoid_overlaps`) and output-space guidance
(:func:`policies.riskflow.guidance.guide`), each as one numba kernel
(:mod:`policies.learned.plan_loops`, its pieces in :mod:`policies.learned.plan_kernels`).

Each step of the torch loops is a few hundred small operations (a rollout, the SAT
gradient of the pairs that can touch, the map term's SDF lookups, the rollout's
vector-Jacobian product, Adam), whose cost on a CPU is dispatch, not arithmetic: the two
loops were two thirds of a default planning cycle. The kernels run every step of every
scene in compiled loops over rows, pairs and plan steps, with the reference's formulas
and stopping rule. They compute in float64 (the reference in the plans' float32), so the
two paths agree to float rounding, not bit for bit
(``tests/policies/learned/test_compiled_plans.py``). Two consequences: a guided row's
trajectory is the float64 rollout of its actions (within 1e-5 m of the float32 one); and
where two boxes touch to within float32 rounding, the paths can disagree on whether they
overlap, and since Adam's first step has the learning rate's length whatever the
gradient's size, such a plan can then differ by one step (0.15 in ``u`` in a constructed
case of a car whose plan ends touching a standing one).

Where they run: numba installed (the ``fast`` extra), CPU tensors, an
:class:`~policies.learned.data.ActionNormalizer` (avoidance), and a map term on a
:class:`~riskflow_env.maps.DrivableMap` or a :class:`~riskflow_env.maps.MapStack`
selection (or none). Otherwise, or with ``RISKFLOW_COMPILED=0`` (the switch of the
compiled simulator step, :mod:`riskflow_env.compiled`), the torch reference runs.
"""

from __future__ import annotations

import functools
import os
from types import ModuleType
from typing import Any

import numpy as np
import torch
from torch import Tensor

from policies.learned import guidance_losses
from policies.learned.data import ActionNormalizer
from policies.learned.guidance_losses import MapTerm
from riskflow_env.compiled import SWITCH, _dynamics_params, _map_tables, import_kernels
from riskflow_env.config import DynamicsConfig
from riskflow_env.maps import DrivableMap, MapStack


@functools.cache
def kernels() -> ModuleType | None:
    """The kernel module, or None where numba cannot be imported or cache its code (a
    warning says so; the reference runs)."""
    return import_kernels("policies.learned.plan_loops", "the compiled planning loops")


def accepts(moving: Tensor, term: MapTerm | None, normalizer: object = None) -> bool:
    """The compiled loops apply (module docstring): ``moving`` the variables (on the CPU),
    ``term`` their map term, ``normalizer`` the plans' decoding (None: decoded already)."""
    if moving.device.type != "cpu":
        return False
    if normalizer is not None and type(normalizer) is not ActionNormalizer:
        return False
    if term is not None and not (
        type(term.map) is DrivableMap or isinstance(term.map, MapStack.Selection)
    ):
        return False
    return os.environ.get(SWITCH, "1") != "0" and kernels() is not None


def avoidance_correction(
    rows: Tensor,
    num_agents: int,
    now: Tensor,
    moving: Tensor,
    share: Tensor | float,
    obstacles: Tensor,
    scored: tuple[Tensor, Tensor, Tensor],
    term: MapTerm | None,
    normalizer: ActionNormalizer,
    dynamics: DynamicsConfig,
    *,
    steps: int,
    step_size: float,
    stop_margin: float,
) -> Tensor:
    """The avoidance loop of ``avoid_overlaps``, compiled: ``(V, H, 2)`` each variable
    row's correction of ``u`` over the scored steps (``share * delta``).

    Args:
        rows: ``(V,)`` the variables' flat ``(scene, agent)`` indices, ascending.
        num_agents: A.
        now: ``(V, 4)`` their states; ``moving`` ``(V, H, 2)`` ``eps + u0``;
            ``share`` ``(V, H, 1)`` the gain, or 1.0.
        obstacles: ``(B, A, H, 4)`` every row's plan (the slow egos standing).
        scored: ``(pairs, length, width)``, ``(B, A, A)`` bool and ``(B, A)`` [m].
        term: the variables' map term (already forgiving), or None.
        normalizer, dynamics: the plans' decoding.
        steps, step_size: Adam's steps and learning rate.
        stop_margin: the stopping rule's margin [m] (and the pairs' slack).
    """
    pairs, length, width = scored
    count, horizon = moving.shape[:2]

    gain = np.ones((count, horizon))
    if isinstance(share, Tensor):  # (V, H or 1, 1): broadcast over the steps, as torch does
        gain = np.ascontiguousarray(np.broadcast_to(_array(share[..., 0]), (count, horizon)))
    mean, std = normalizer.mean, normalizer.std
    correction = kernels().avoid_scenes(
        (rows // num_agents).numpy(), (rows % num_agents).numpy(), _array(now),
        _array(moving), gain, _array(obstacles), _array(length), _array(width), pairs.numpy(),
        *_map_inputs(term, count, horizon),
        np.array([mean[0], mean[1], std[0], std[1]], dtype=np.float64),
        _dynamics_params(dynamics), steps, step_size, stop_margin, stop_margin,
        moving.dtype == torch.float32,
    )  # fmt: skip
    return torch.from_numpy(correction).to(moving.dtype)


def guidance_steps(
    objective: Any, u_c: Tensor, lower: Tensor, upper: Tensor, config: Any
) -> tuple[Tensor, Tensor, Tensor]:
    """The steps of output-space guidance (``policies.riskflow.guidance._guide_scenes``'
    loop), compiled: the guided residual ``u_c`` (C, T, 2) after ``config.steps`` steps
    within ``lower``/``upper``, its rollout (C, T, 4), and (steps + 1, C, 2) ``(L_adv,
    L_map)`` of each row before each step and after the last. ``objective`` is the loop's
    ``_Objective`` (its rows, targets and terms)."""
    count, length = u_c.shape[:2]
    horizon = min(length, objective.horizon or length)
    term, separation = objective.map_term, objective.separation
    if separation is None:
        sep_pairs, sizes = np.zeros((0, 2), np.int64), np.zeros((count, 2))
        fixed = np.zeros((0, horizon, 4))
    else:
        box_length, box_width, pairs = (box[0] for box in separation.boxes)
        sep_pairs = torch.nonzero(pairs).numpy()
        sizes = np.stack([_array(box_length), _array(box_width)], axis=-1)
        fixed = np.zeros((0, horizon, 4)) if separation.fixed is None else _array(separation.fixed)
    floor = objective.floor
    keep = guidance_losses.LAMBDA_KEEP_MOVING  # read at the call, as the reference does
    lambdas = (config.lambda_adv, config.lambda_map, objective.lambda_sep, keep)
    u, plans, losses = kernels().guide_rows(
        _array(objective.state), _array(objective.offset), _array(objective.std).reshape(-1),
        _array(u_c), _array(lower), _array(upper), _array(objective.target_xy),
        objective.target_valid.numpy(), horizon, *_map_inputs(term, count, length), sep_pairs,
        sizes, fixed,
        floor is not None, np.zeros(count) if floor is None else _array(floor),
        np.array(lambdas, dtype=np.float64), _dynamics_params(objective.dynamics),
        config.steps, config.resolved_step_size, config.optimizer != "gradient",
        u_c.dtype == torch.float32,
    )  # fmt: skip
    return tuple(torch.from_numpy(x).to(u_c.dtype) for x in (u, plans, losses))


def _array(x: Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().numpy(), dtype=np.float64)


def _map_inputs(term: MapTerm | None, count: int, horizon: int) -> tuple:
    """The kernels' map arguments for ``count`` rows: ``use_map``, frames (count, 5),
    along and across (count, 9), margins (count,), weights (horizon,), and the rasters."""
    if term is None:
        frames, along, across = np.zeros((count, 5)), *np.zeros((2, count, 9))
        margins, weights = np.zeros(count), np.zeros(horizon)
        flat, grid_int, grid_float = np.zeros(4), np.zeros((1, 3), np.int64), np.zeros((1, 4))
        rasters = (flat, grid_int, grid_float, np.zeros(count, np.int64))
        return (False, frames, along, across, margins, weights, *rasters)
    if term.weights.shape[0] != horizon:  # the reference fails to broadcast too
        raise ValueError(
            f"the map term scores {term.weights.shape[0]} plan steps, the plans have {horizon}"
        )
    if isinstance(term.map, MapStack.Selection) and len(term.map.index) != count:
        raise ValueError(f"the map term selects {len(term.map.index)} maps for {count} rows")
    parts = (term.origin_x, term.origin_y, term.yaw, term.cos, term.sin)  # (1 or V, 1)
    frames = np.stack([np.broadcast_to(_array(p)[:, 0], (count,)) for p in parts], axis=-1)
    margin = term.margin
    margins = np.broadcast_to(
        _array(margin).reshape(-1) if isinstance(margin, Tensor) else np.float64(margin),
        (count,),
    ).copy()
    lookup = term.map
    if isinstance(lookup, MapStack.Selection) and isinstance(lookup.index, Tensor):
        lookup = lookup.stack.select(lookup.index.numpy())  # the rasters' numpy tables
    rasters = _map_tables(lookup, (count,), count)
    along, across = _array(term.along[:, 0]), _array(term.across[:, 0])
    return (True, frames, along, across, margins, _array(term.weights), *rasters)


__all__ = ["accepts", "avoidance_correction", "guidance_steps", "kernels"]
