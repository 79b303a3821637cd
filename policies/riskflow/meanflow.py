"""The MeanFlow objective in action space, with RiskFlow's trajectory-space loss.

Notation (docs/explanation/method.md; noise at t = 0, data at t = 1), per agent plan:

* ``a*``: normalised ground-truth actions ``(B, A, T, 2)``; ``eps ~ N(0, I)`` alike;
* ``z_t = (1 - t) eps + t a*`` and ``v = a* - eps`` (the conditional velocity);
* ``u = u_theta(z_t, t, r; C)`` the average velocity from ``t`` to ``r >= t``.

MeanFlow identity (Geng et al. 2025, eq. 6, in this convention)::

    u(z_t, t, r) = v(z_t, t) - (t - r) du/dt,   du/dt = v . d_z u + d_t u

``du/dt`` is the Jacobian-vector product of ``u_theta`` with tangents ``(dz, dt, dr) =
(v, 1, 0)``, computed with ``torch.func.jvp`` in the same pass as ``u``; the scene
context ``C`` does not depend on ``(z, t, r)`` and is computed once, outside the JVP.
The MeanFlow target ``u_tgt = v - (t - r) sg(du/dt)`` would be regressed directly; the
RiskFlow paper instead reconstructs the action plan::

    a_hat = eps + u + (t - r) * clip(sg(du/dt), -c, c),   c = 0.03

(``a_hat - a* = u - u_tgt`` before clipping), de-normalises it, rolls it out through
``riskflow_env.dynamics.rollout`` from every agent's current state and minimises the
masked squared error to the ground-truth future positions (optionally headings).
Gradients flow through ``u`` only.

Caveat: ``rollout`` clips actions to the dynamics bounds, so a reconstructed action
beyond a bound gets no gradient through that step; and positions integrate the actions
twice, so they barely constrain high-frequency action errors. ``metrics["action_mse"]``
(the plain action-space MeanFlow error) shows both; a ``weights.action > 0`` adds it to
the loss.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from policies.learned.data import Normalizer
from policies.learned.distributed import Shard
from policies.learned.encoder import SceneContext
from policies.learned.generator import RiskFlowGenerator
from policies.learned.trajectory_loss import (
    POSITION_ONLY,
    LossWeights,
    action_mse,
    target_actions,
    trajectory_loss,
)
from policies.learned.window_types import WindowBatch
from policies.riskflow.time_sampler import TimeSampler
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import DEFAULT_CONFIG

DUDT_CLIP = 0.03  # c: bound of sg(du/dt) in the reconstruction (RiskFlow paper).


def _time_as(t: Tensor) -> Tensor:
    """``t (B,)`` or ``(B, A)`` reshaped to broadcast against ``x (B, A, T, 2)``."""
    return t.reshape(t.shape[0], -1, 1, 1)


def _check(batch: WindowBatch, eps: Tensor, t: Tensor, r: Tensor) -> None:
    batch.require_future("the MeanFlow loss")
    if tuple(eps.shape) != tuple(batch.actions.shape):
        raise ValueError(
            f"eps must have the shape of batch.actions (B, A, T, 2) = "
            f"{tuple(batch.actions.shape)}, got {tuple(eps.shape)}"
        )
    batch_size = eps.shape[0]
    for name, time in (("t", t), ("r", r)):
        if time.shape not in ((batch_size,), tuple(eps.shape[:2])):
            raise ValueError(f"{name} must be (B,) or (B, A), got {tuple(time.shape)}")
    if bool((r < t).any()):
        raise ValueError("the MeanFlow times need t <= r (noise at 0, data at 1)")


def average_velocity_jvp(
    u_fn: Callable[[Tensor, Tensor, Tensor], Tensor], z_t: Tensor, t: Tensor, r: Tensor, v: Tensor
) -> tuple[Tensor, Tensor]:
    """``u = u_fn(z_t, t, r)`` and its total derivative along the flow, in one pass.

    ``du/dt = v . d_z u + d_t u`` is the JVP of ``u_fn`` with tangents ``(dz, dt, dr) =
    (v, 1, 0)`` (MeanFlow, Geng et al. 2025, eq. 8), by forward-mode AD
    (``torch.func.jvp``). ``u`` keeps its autograd graph; ``du/dt`` should be
    detached by the caller (the stop-gradient of the MeanFlow target).

    Args:
        u_fn: ``(z, t, r) -> u``, e.g. the MeanFlow head with a fixed context.
        z_t: ``(B, ...)`` point on the path.
        t: ``(B,)`` (or ``(B, A)``) times.
        r: like ``t``.
        v: like ``z_t``, the velocity ``dz_t/dt`` (``a* - eps`` in training).

    Returns:
        ``(u, du/dt)``, both shaped like ``u_fn``'s output.
    """
    return torch.func.jvp(u_fn, (z_t, t, r), (v, torch.ones_like(t), torch.zeros_like(r)))


def meanflow_target(v: Tensor, dudt: Tensor, t: Tensor, r: Tensor) -> Tensor:
    """MeanFlow identity target ``u_tgt = v - (t - r) du/dt`` (Geng et al. 2025, eq. 6/10).

    ``t, r`` must broadcast against ``v`` (e.g. ``(B, 1, 1, 1)``). Equals the true
    average velocity when ``v`` is the marginal velocity and ``du/dt`` is exact.
    """
    return v - (t - r) * dudt


def meanflow_loss(
    model: RiskFlowGenerator,
    batch: WindowBatch,
    normalizer: Normalizer,
    eps: Tensor,
    t: Tensor,
    r: Tensor,
    clip: float = DUDT_CLIP,
    weights: LossWeights = POSITION_ONLY,
    dynamics: DynamicsConfig = DEFAULT_CONFIG,
) -> tuple[Tensor, dict[str, Tensor]]:
    """RiskFlow's MeanFlow objective (see the module docstring).

    Args:
        model: the generator.
        batch: training windows (``docs/how-to/windows.md``), with the future fields.
        normalizer: action normalisation (``normalize`` / ``denormalize``).
        eps: ``(B, A, T, 2)`` standard normal noise.
        t: ``(B,)`` or ``(B, A)`` start times in [0, 1] (``time_sampler.TimeSampler``).
        r: like ``t``, end times ``r >= t``.
        clip: ``c``, bound of ``sg(du/dt)`` in the reconstruction.
        weights: of the loss's terms. ``action`` weighs ``action_mse`` (0: RiskFlow's
            pure trajectory-space loss): positions integrate actions twice, so they
            barely see high-frequency action errors; this term (the MeanFlow regression
            itself) pins those down.
        dynamics: time step and bounds of the rollout.

    Returns:
        ``(loss, metrics)``: the scalar loss and detached scalar metrics: those of
        :func:`trajectory_loss`, ``loss``, ``action_mse`` (normalised ``|a_hat - a*|^2``
        on valid actions: MeanFlow's own regression error), ``dudt_abs`` (mean
        ``|du/dt|``) and ``dudt_clipped`` (share of entries beyond ``clip``).
    """
    _check(batch, eps, t, r)
    scene = model.encode(batch)
    a_star = target_actions(batch, normalizer)
    t_, r_ = _time_as(t), _time_as(r)
    z_t = (1.0 - t_) * eps + t_ * a_star
    v = a_star - eps

    def u_theta(z: Tensor, t_in: Tensor, r_in: Tensor) -> Tensor:
        return model.average_velocity(z, t_in, r_in, scene)

    u, dudt = average_velocity_jvp(u_theta, z_t, t, r, v)
    dudt = dudt.detach()
    a_hat = eps + u + (t_ - r_) * dudt.clamp(-clip, clip)
    loss, metrics = _loss(a_hat, a_star, batch, scene, normalizer, weights, dynamics)
    metrics["dudt_abs"] = dudt.abs().mean()
    metrics["dudt_clipped"] = (dudt.abs() > clip).to(dudt.dtype).mean()
    return loss, metrics


def flow_matching_loss(
    model: RiskFlowGenerator,
    batch: WindowBatch,
    normalizer: Normalizer,
    eps: Tensor,
    t: Tensor,
    weights: LossWeights = POSITION_ONLY,
    dynamics: DynamicsConfig = DEFAULT_CONFIG,
) -> tuple[Tensor, dict[str, Tensor]]:
    """Plain flow matching (``r = t``, no JVP): ``a_hat = eps + u_theta(z_t, t, t; C)``.

    The reference the MeanFlow objective is compared with (speed benchmark,
    ablations); same arguments and metrics as :func:`meanflow_loss` without the
    ``du/dt`` ones.
    """
    _check(batch, eps, t, t)
    scene = model.encode(batch)
    a_star = target_actions(batch, normalizer)
    t_ = _time_as(t)
    u = model.average_velocity((1.0 - t_) * eps + t_ * a_star, t, t, scene)
    return _loss(eps + u, a_star, batch, scene, normalizer, weights, dynamics)


def _loss(
    a_hat: Tensor,
    a_star: Tensor,
    batch: WindowBatch,
    scene: SceneContext,
    normalizer: Normalizer,
    weights: LossWeights,
    dynamics: DynamicsConfig,
) -> tuple[Tensor, dict[str, Tensor]]:
    """Trajectory loss (with its penalties) plus ``weights.action * action_mse``."""
    loss, metrics = trajectory_loss(a_hat, batch, scene, normalizer, weights, dynamics)
    action_error = action_mse(a_hat, a_star, batch, scene)
    if weights.action:
        loss = loss + weights.action * action_error
    metrics["action_mse"] = action_error.detach()
    metrics["loss"] = loss.detach()
    return loss, metrics


class OneStepFlowMatching:
    """A flow-matching model (trained with ``r = t`` only) seen as a one-step sampler.

    Its network is the instantaneous velocity ``v(z, t) = u_theta(z, t, t)``; one Euler
    step from noise is ``a = eps + v(eps, 0)``. This adapter answers
    ``average_velocity(z, t, r)`` with ``u_theta(z, t, t)``, so ``sampler.sample``
    (which asks for ``u(eps, 0, 1)``) takes exactly that step.
    """

    def __init__(self, model: RiskFlowGenerator) -> None:
        self.model = model
        self.config = model.config

    def encode(self, batch: WindowBatch) -> SceneContext:
        """The wrapped model's scene context."""
        return self.model.encode(batch)

    def average_velocity(self, z: Tensor, t: Tensor, r: Tensor, scene: SceneContext) -> Tensor:
        """``u_theta(z, t, t; C)``; ``r`` is ignored."""
        return self.model.average_velocity(z, t, t, scene)


class MeanFlowObjective:
    """The ``--generator meanflow`` objective of the training loop
    (:func:`policies.learned.trainer.fit`).

    Per step: ``(t, r)`` from ``times`` after the loop's ``eps``, both from the run's
    seeded generator (so ``--resume`` stays exact), and
    :func:`meanflow_loss` (:func:`flow_matching_loss` for the plain flow-matching
    reference, whose validation samples one Euler step, :class:`OneStepFlowMatching`).

    Args:
        times: the ``(t, r)`` sampler.
        flow_matching: train the flow-matching reference (``r = t``).
    """

    kind = "meanflow"

    def __init__(self, times: TimeSampler, flow_matching: bool = False) -> None:
        self.times, self.flow_matching = times, flow_matching

    def loss(
        self,
        model: RiskFlowGenerator,
        batch: WindowBatch,
        normalizer: Normalizer,
        eps: Tensor,
        generator: torch.Generator,
        weights: LossWeights,
        shard: Shard,
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """One step's loss and metrics (``weights`` as :func:`meanflow_loss`); ``(t, r)``
        are drawn for ``shard``'s whole global batch and its rows taken."""
        t, r = self.times(shard.total, generator=generator, device=eps.device)
        t, r = shard.rows(t), shard.rows(r)
        if self.flow_matching:
            return flow_matching_loss(model, batch, normalizer, eps, t, weights)
        return meanflow_loss(model, batch, normalizer, eps, t, r, weights=weights)

    def sampler(self, model: RiskFlowGenerator) -> RiskFlowGenerator | OneStepFlowMatching:
        """What validation samples: the model's one step (one Euler step for flow matching)."""
        return OneStepFlowMatching(model) if self.flow_matching else model
