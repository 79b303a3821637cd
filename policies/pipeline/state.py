"""``PlannerState``: what a scene policy keeps of one scene between planning cycles.

A pipeline policy (:mod:`policies.pipeline.policy`) holds no per-scene attributes of its
own: everything that persists from one cycle to the next (the plan buffer that the env
steps read, the schedule, the noise stream's position, what the last cycle decided) is
one value of this type, as Waymax's actors carry theirs. A cycle takes the states of the
scenes it plans and returns their new ones; a batch of scenes is a list of them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from policies.learned.ranking import Ranking


@dataclass
class PlannerState:
    """One scene's planner state (module docstring).

    Attributes:
        seed: noise seed of this scene: the noise of cycle ``c`` of episode ``e`` comes
            from ``(seed, e, c)``.
        episode: ``reset`` count from 0 (-1: never reset).
        cycles: planning cycles of this episode so far.
        plan_step: env step of the last cycle (None: no plan yet).
        plan_actions: (A, T, 2) the plan buffer (accel [m/s^2], yaw rate [rad/s]) per env
            slot; zeros for slots without a plan.
        plans: (A, T, 4) world-frame states (x, y [m], v [m/s], psi [rad]) after each
            plan step; NaN rows for slots without a plan (None: no plan yet).
        base_plans: (A, T, 4) the unguided alternative of ``plans`` (the same rows
            outside ``A_c``).
        base_actions: (A, T, 2) the actions of ``base_plans`` (zeros for slots without a
            plan; None: no plan yet).
        plan_mask: (A,) bool, the slots with a plan.
        controllable: (A,) bool, ``A_c`` of the last cycle (target ``"ego"``: the
            attacker, kept by the next cycle while it is eligible).
        names: the env's slot names.
        ranking: how ``A_c`` was chosen (window slot order), or None.
        noise: the cycle's noise (window slot order), or None.
        guidance_losses: (N, 2) ``L_adv``, ``L_map`` per guidance step, or None.
        timings: [s] per phase of the cycle, and ``"total"``.
        extras: a method's own per-cycle outputs (STRIVE-style: ``latent``,
            ``prior_losses``).
    """

    seed: int
    episode: int = -1
    cycles: int = 0
    plan_step: int | None = None
    plan_actions: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 2)))
    plans: np.ndarray | None = None
    base_plans: np.ndarray | None = None
    base_actions: np.ndarray | None = None
    plan_mask: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    controllable: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    names: tuple[str, ...] = ()
    ranking: Ranking | None = None
    noise: torch.Tensor | None = None
    guidance_losses: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)
    extras: dict[str, Any] = field(default_factory=dict)

    def restarted(self, seed: int | None = None) -> PlannerState:
        """A state with no plan (a new episode keeps the episode count; ``seed`` resets it,
        as a fresh policy built with that seed)."""
        if seed is not None:
            return PlannerState(seed=int(seed))
        return PlannerState(seed=self.seed, episode=self.episode)

    def noise_source(self, device: torch.device) -> torch.Generator:
        """The random stream of this scene's next cycle, seeded with ``(seed, episode,
        cycles)``: the same seed gives the same noise, bit for bit, on one machine."""
        entropy = [self.seed, self.episode, self.cycles]
        seed = int(np.random.SeedSequence(entropy).generate_state(1)[0])
        return torch.Generator(device=device).manual_seed(seed)

    def replace(self, **changes: Any) -> PlannerState:
        """A copy with ``changes``."""
        return dataclasses.replace(self, **changes)


__all__ = ["PlannerState"]
