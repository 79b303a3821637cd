"""What output-space guidance (:mod:`policies.riskflow.guidance`) takes and returns, for
one scene or a batch of B scenes: the scene's base plans and geometry
(:class:`GuidanceScene`), its options (:class:`GuidanceConfig`) and the guided plans
(:class:`GuidanceResult`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from torch import Tensor

from policies.learned.guidance_losses import ObjectiveConfig
from riskflow_env.config import is_integer
from riskflow_env.maps import DrivableMap


@dataclass(frozen=True)
class GuidanceScene:
    """One scene's plans and what guidance needs about it (torch, scene frame), or B
    scenes' (batched planning: a leading B axis on every tensor, agents padded to A).

    Attributes:
        eps: (A, T, 2) noise, normalised; (B, A, T, 2) for B scenes.
        u0: (A, T, 2) base residual ``u_theta(eps, 0, 1; C)``.
        state: (A, 4) current states (x, y [m], v [m/s], psi [rad]).
        length: (A,) [m].
        width: (A,) [m].
        agent_mask: (A,) bool agents present (False on padding).
        base_actions: (A, T, 2) :func:`~policies.learned.sampler.decode_plans` of ``eps + u0``.
        base_trajectories: (A, T, 4) their rollout.
        drivable_map: the scene's map (world frame); for B scenes a
            :class:`~riskflow_env.maps.MapStack` of their maps in scene order, or one map
            they all share; None drops ``L_map``.
        frame: (3,) world pose (x [m], y [m], psi [rad]) of the scene frame; (B, 3).
        ego: slot of the ego (in every scene).
    """

    eps: Tensor
    u0: Tensor
    state: Tensor
    length: Tensor
    width: Tensor
    agent_mask: Tensor
    base_actions: Tensor
    base_trajectories: Tensor
    drivable_map: DrivableMap | None
    frame: Tensor
    ego: int = 0


@dataclass(frozen=True)
class GuidanceResult:
    """Guided plans: ``u``, ``actions`` (A, T, 2), ``trajectories`` (A, T, 4) (base plans
    outside ``A_c``) and ``losses`` (steps + 1, 2): ``(L_adv [m], L_map [m^2])`` before
    each step and after the last. For B scenes: (B, A, ...) and losses (steps + 1, B, 2),
    each scene's own."""

    u: Tensor
    actions: Tensor
    trajectories: Tensor
    losses: Tensor


OPTIMIZERS = ("gradient", "adam")
# The default Adam step per target: 0.01 with the paper's target (it keeps the guided traffic
# nearest the log and still collides more than STRIVE-style, docs/explanation/results.md section 4);
# 0.1, the paper's step, with target "ego", where smaller steps hit the ego far less often.
STEP_SIZES = {"others": 0.01, "ego": 0.1}
MAX_STEPS = 1000  # [-] largest K_g (each step is a backward pass over the plans: ~ms)


@dataclass(frozen=True)
class GuidanceConfig(ObjectiveConfig):
    """Options of output-space guidance: the shared objective's
    (:class:`~policies.learned.guidance_losses.ObjectiveConfig`: ``lambda_adv``,
    ``lambda_map``, ``horizon``, ``target``, ``map_margin``, ``map_decay``,
    ``lambda_sep``) and the optimiser's.

    Attributes:
        steps: ``K_g`` guidance steps (0: the base plans), at most ``MAX_STEPS``.
        step_size: the Adam learning rate [normalised action units per step], or
            ``gamma`` [normalised action units per unit of gradient] for ``"gradient"``
            (e.g. 3e-3 with the default weights); None (default): ``STEP_SIZES[target]``,
            0.01 with target ``"others"`` and the paper's 0.1 with ``"ego"``.
        optimizer: ``"adam"`` (the default, :mod:`policies.learned.adam`) or
            ``"gradient"`` (plain steps, the paper's).
    """

    steps: int = 30
    step_size: float | None = None
    optimizer: str = "adam"

    @classmethod
    def of(
        cls,
        config,
        steps: int,
        step_size: float | None,
        optimizer: str,
        lambda_sep: float,
    ) -> GuidanceConfig:
        """The guidance of an adversary: the objective of its shared options ``config``
        (:meth:`~policies.learned.adversary_config.AdversaryConfig.objective`) and these."""
        return cls(
            steps=steps,
            step_size=step_size,
            optimizer=optimizer,
            lambda_sep=lambda_sep,
            **config.objective(),
        )

    @property
    def resolved_step_size(self) -> float:
        """The step in use: ``step_size``, or the target's default when it is None (so a
        copy with another ``target``, e.g. a curriculum's, takes that target's)."""
        return STEP_SIZES[self.target] if self.step_size is None else self.step_size

    def checks(self) -> list[tuple[bool, str]]:
        """The objective's rules and the optimiser's."""
        steps_ok = is_integer(self.steps)
        return super().checks() + [
            (
                steps_ok and 0 <= self.steps <= MAX_STEPS,
                f"steps must be an int in [0, {MAX_STEPS}]",
            ),
            (
                self.step_size is None or (math.isfinite(self.step_size) and self.step_size > 0),
                "step_size must be None or a number > 0",
            ),
            (self.optimizer in OPTIMIZERS, f"optimizer must be one of {OPTIMIZERS}"),
        ]


__all__ = [
    "MAX_STEPS",
    "OPTIMIZERS",
    "STEP_SIZES",
    "GuidanceConfig",
    "GuidanceResult",
    "GuidanceScene",
]
