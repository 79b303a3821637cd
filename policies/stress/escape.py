"""Hindsight escape search: could the ego have kept clear, the others doing what they did?

A collision is *avoidable* when some trajectory of the ego, within its dynamics bounds,
from a reaction point on, keeps clear of every other vehicle (their executed trajectories
held fixed: hindsight, as STRIVE's solvability check, Rempe et al., CVPR 2022) and on the
road. :func:`find_escape` looks for one; the trajectory it finds is the *witness*.

The search, vectorised over candidates, agents and time:

1. **Controls.** An ego trajectory is its actions (accel [m/s^2], yaw rate [rad/s]) at
   knots every ``knot_interval`` seconds, linear in between, kept inside the
   :class:`~riskflow_env.config.DynamicsConfig` bounds, rolled out by
   :func:`riskflow_env.dynamics.rollout` (the env's own integrator).
2. **Sampled maneuvers.** ``samples`` candidates: a grid of constant controls (brake,
   keep, accelerate x straight, left, right) and uniform random knots (a third of them
   with gentle yaw rates), all scored at once.
3. **Refinement.** The ``refine`` best candidates (least penetration) take ``steps``
   projected Adam steps on the soft cost ``sum relu(margin - separation)`` over the other
   vehicles and time, plus the footprint's SDF excess over the road
   (:func:`riskflow_env.geometry.separation` and ``DrivableMap.sdf_at``, differentiated by
   autograd). The search stops at the first candidate that passes the hard check.
4. **Hard check.** Every step: box separation to every present vehicle ``>= CLEARANCE``
   and no footprint sample deeper off the road than the ego started.

Not found within the budget means *not shown avoidable*, not *unavoidable*:
:meth:`EscapeSearch.scaled` gives a longer search to measure how often that flips.

Where numba is installed (the ``fast`` extra) steps 2 to 4 run as numba kernels
(:mod:`policies.stress.escape_kernels`) with the gradients in closed form; the torch code
here is their reference and runs without numba or with ``RISKFLOW_COMPILED=0``. The two
agree to float rounding, and so give the same verdicts but where a candidate passes the
hard check by less than that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import ModuleType
from typing import NamedTuple

import numpy as np
import torch

from policies.dataclass_cli import check_at_least
from riskflow_env.compiled import _dynamics_params, _map_tables
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import rollout
from riskflow_env.geometry import _ACROSS, _ALONG, footprint_points, separation
from riskflow_env.kernel_loading import optional_kernels
from riskflow_env.maps import DrivableMap

CLEARANCE = 0.1  # [m] least box separation a witness keeps to every other vehicle
ROAD_SLACK = 0.1  # [m] the soft cost's road term starts this far inside the hard check
STRAIGHT_SHARE = 1 / 3  # share of random candidates with yaw rates within 0.2 of the bound


@dataclass(frozen=True)
class EscapeSearch:
    """The search budget (module docstring).

    Attributes:
        samples: sampled maneuvers scored at once.
        refine: best samples refined by gradient steps.
        steps: projected Adam steps per refined sample.
        knot_interval: [s] time between control knots.
        learning_rate: Adam step [m/s^2, rad/s] on the knot controls.
        margin: [m] clearance the soft cost aims for (above ``CLEARANCE``).
        seed: random maneuvers' seed (same seed, same verdict).
    """

    samples: int = 1024
    refine: int = 32
    steps: int = 240
    knot_interval: float = 0.5
    learning_rate: float = 0.3
    margin: float = 0.5
    seed: int = 0

    def __post_init__(self) -> None:
        check_at_least(self, dict.fromkeys(("samples", "refine", "steps"), 1), owner="EscapeSearch")
        for name in ("knot_interval", "learning_rate", "margin"):
            if not getattr(self, name) > 0:
                raise ValueError(f"EscapeSearch.{name} must be > 0, got {getattr(self, name)}")

    def scaled(self, factor: int) -> EscapeSearch:
        """The same search with ``factor`` times the samples, refined rows and steps."""
        return EscapeSearch(
            self.samples * factor, self.refine * factor, self.steps * factor,
            self.knot_interval, self.learning_rate, self.margin, self.seed,
        )  # fmt: skip


@dataclass(frozen=True)
class Obstacles:
    """The other vehicles over the search horizon, held fixed.

    Attributes:
        xy: (N, H, 2) [m] centres at the H steps after the reaction point.
        yaw: (N, H) [rad].
        length, width: (N,) [m].
        present: (N, H) bool, the vehicle is there (False after it left the scene).
    """

    xy: np.ndarray
    yaw: np.ndarray
    length: np.ndarray
    width: np.ndarray
    present: np.ndarray


@dataclass(frozen=True)
class Escape:
    """What the search found.

    Attributes:
        found: a trajectory passed the hard check (the collision is avoidable).
        actions: (H, 2) the best candidate's actions (the witness when ``found``).
        states: (H + 1, 4) its states, the reaction state first.
        clearance: [m] its least separation to any vehicle over the horizon.
        road_depth: [m] its deepest footprint sample off the road (<= 0: on the road).
        candidates: trajectories evaluated (samples plus refinement steps).
    """

    found: bool
    actions: np.ndarray
    states: np.ndarray
    clearance: float
    road_depth: float
    candidates: int


def find_escape(
    start: np.ndarray,
    size: tuple[float, float],
    obstacles: Obstacles,
    drivable_map: DrivableMap | None,
    dynamics: DynamicsConfig,
    search: EscapeSearch = EscapeSearch(),
) -> Escape:
    """Search the ego's actions for a trajectory that keeps clear and on the road.

    Args:
        start: (4,) the ego's state at the reaction point (x, y [m], v [m/s], psi [rad]).
        size: the ego's (length, width) [m].
        obstacles: the other vehicles at the ``H`` following steps.
        drivable_map: the road (None: no road constraint).
        dynamics: the ego's bounds and time step.
        search: the budget.

    Returns:
        The :class:`Escape`; ``found`` says whether the collision was shown avoidable.
    """
    horizon = obstacles.xy.shape[1]
    if horizon < 1:
        raise ValueError(f"obstacles must cover at least one step, got {horizon}")
    problem = _Problem(start, size, obstacles, drivable_map, dynamics, search)
    solver = _CompiledProblem.of(problem) or problem
    generator = torch.Generator().manual_seed(search.seed)
    knots = problem.sampled_knots(generator)
    with torch.no_grad():
        score = solver.evaluate(knots)
    evaluated = knots.shape[0]
    if not bool(score.feasible.any()):
        best = torch.argsort(score.cost)[: search.refine]
        knots, steps = solver.refine(knots[best].clone())
        evaluated += best.numel() * steps
        with torch.no_grad():
            score = solver.evaluate(knots)
    pick = int(torch.argmax(score.feasible.double() - score.cost / (1.0 + score.cost.max())))
    if solver is not problem:  # the least separation of the pick without the skipped pairs
        knots, pick = knots[pick : pick + 1], 0
        score = solver.evaluate(knots, exact=True)
    return Escape(
        found=bool(score.feasible[pick]),
        actions=problem.actions(knots[pick : pick + 1])[0].numpy(),
        states=torch.cat((problem.start[None], score.states[pick])).numpy(),
        clearance=float(score.clearance[pick]),
        road_depth=float(score.road_depth[pick]),
        candidates=evaluated,
    )


class _Score(NamedTuple):
    """Candidates' soft cost (S,), hard check (S,) bool, states (S, H, 4), least
    separation (S,) [m] and deepest footprint sample off the road (S,) [m]."""

    cost: torch.Tensor
    feasible: torch.Tensor
    states: torch.Tensor
    clearance: torch.Tensor
    road_depth: torch.Tensor


class _Problem:
    """One search: the start, the obstacles and the road as float64 tensors."""

    def __init__(self, start, size, obstacles, drivable_map, dynamics, search) -> None:
        self.dynamics, self.map, self.search = dynamics, drivable_map, search
        self.start = torch.as_tensor(np.asarray(start, dtype=np.float64))
        self.length, self.width = (float(x) for x in size)
        self.xy = torch.as_tensor(np.asarray(obstacles.xy, dtype=np.float64))
        self.yaw = torch.as_tensor(np.asarray(obstacles.yaw, dtype=np.float64))
        self.other_length = torch.as_tensor(np.asarray(obstacles.length, dtype=np.float64))
        self.other_width = torch.as_tensor(np.asarray(obstacles.width, dtype=np.float64))
        self.present = torch.as_tensor(np.asarray(obstacles.present, dtype=bool))
        self.horizon = self.xy.shape[1]
        self.knot_steps = max(1, round(search.knot_interval / dynamics.dt))
        self.num_knots = self.horizon // self.knot_steps + 2
        self.interpolation = torch.as_tensor(_interpolation(self.horizon, self.knot_steps))
        self.low = torch.tensor([dynamics.accel_min, -dynamics.yaw_rate_max], dtype=torch.float64)
        self.high = torch.tensor([dynamics.accel_max, dynamics.yaw_rate_max], dtype=torch.float64)
        self.road_allowance = max(0.0, float(self.road_depth(self.start[None, :])[0]))

    def sampled_knots(self, generator: torch.Generator) -> torch.Tensor:
        """(S, K, 2) knot controls: the constant-control grid, then random knots."""
        accel = torch.linspace(float(self.low[0]), float(self.high[0]), 7, dtype=torch.float64)
        yaw = torch.tensor([0.0, -0.1, 0.1, -0.3, 0.3], dtype=torch.float64)
        grid = torch.cartesian_prod(accel, yaw * float(self.high[1]))  # (35, 2)
        grid = grid[: self.search.samples, None, :].expand(-1, self.num_knots, 2)
        count = self.search.samples - grid.shape[0]
        unit = torch.rand((count, self.num_knots, 2), generator=generator, dtype=torch.float64)
        knots = self.low + (self.high - self.low) * unit
        gentle = torch.arange(count) < round(STRAIGHT_SHARE * count)
        knots[gentle, :, 1] *= 0.2
        return torch.cat((grid, knots))

    def project(self, knots: torch.Tensor) -> torch.Tensor:
        """Knot controls clipped to the dynamics bounds."""
        return torch.maximum(torch.minimum(knots, self.high), self.low)

    def refine(self, knots: torch.Tensor) -> tuple[torch.Tensor, int]:
        """Projected Adam on the soft cost until a row passes the hard check: the knots
        and the steps taken."""
        knots.requires_grad_(True)
        optimizer = torch.optim.Adam([knots], lr=self.search.learning_rate)
        for step in range(self.search.steps):
            score = self.evaluate(knots)
            if bool(score.feasible.any()):
                return knots.detach(), step
            optimizer.zero_grad()
            score.cost.sum().backward()
            optimizer.step()
            with torch.no_grad():
                knots.copy_(self.project(knots))
        return knots.detach(), self.search.steps

    def actions(self, knots: torch.Tensor) -> torch.Tensor:
        """(S, H, 2) actions, linear between the knots (S, K, 2)."""
        return torch.einsum("hk,skc->shc", self.interpolation, knots)

    def road_depth(self, states: torch.Tensor) -> torch.Tensor:
        """(...) deepest footprint sample off the road [m] of states (..., 4)."""
        if self.map is None:
            return torch.full(states.shape[:-1], -np.inf, dtype=states.dtype)
        points = footprint_points(states[..., :2], states[..., 3], self.length, self.width)
        return self.map.sdf_at(points).amax(dim=-1)

    def evaluate(self, knots: torch.Tensor) -> _Score:
        """The :class:`_Score` of knot controls (S, K, 2)."""
        states = rollout(self.start, self.actions(knots), self.dynamics, clip=False)
        gap = separation(
            states[:, None, :, :2],
            states[:, None, :, 3],
            self.length,
            self.width,
            self.xy,
            self.yaw,
            self.other_length[:, None],
            self.other_width[:, None],
        )  # fmt: skip  (S, N, H)
        gap = torch.where(self.present, gap, torch.full_like(gap, np.inf))
        depth = self.road_depth(states)  # (S, H)
        excess = depth - self.road_allowance
        margin = CLEARANCE + self.search.margin
        road = torch.relu(excess + ROAD_SLACK).sum(dim=1)
        cost = torch.relu(margin - gap).sum(dim=(1, 2)) + road
        clear = gap.flatten(1).amin(dim=1) if gap.shape[1] else torch.full_like(cost, np.inf)
        feasible = (clear >= CLEARANCE) & (excess.amax(dim=1) <= 0)
        return _Score(cost, feasible, states.detach(), clear.detach(), depth.amax(dim=1).detach())


class _CompiledProblem:
    """The search's two phases as numba kernels (:mod:`policies.stress.escape_kernels`),
    with :class:`_Problem`'s ``evaluate`` and ``refine``: several times faster, equal to
    float rounding (``tests/policies/stress/test_escape.py``)."""

    def __init__(self, problem: _Problem, kernels: ModuleType) -> None:
        self.problem, self.kernels = problem, kernels
        numpy = {name: getattr(problem, name).numpy() for name in ("xy", "yaw", "present")}
        length, width = problem.other_length.numpy(), problem.other_width.numpy()
        radius = 0.5 * np.sqrt(length**2 + width**2)
        self.low, self.high = problem.low.numpy(), problem.high.numpy()
        self.scene = (
            problem.interpolation.numpy(),
            problem.start.numpy(),
            _dynamics_params(problem.dynamics),
            np.concatenate([numpy["xy"], numpy["yaw"][..., None]], axis=-1),
            np.stack([length, width, radius], axis=-1).reshape(-1, 3),
            numpy["present"],
            np.array([problem.length, problem.width]),
            self._road(problem),
            (
                CLEARANCE + problem.search.margin,
                problem.road_allowance,
                0.5 * math.hypot(problem.length, problem.width),
                ROAD_SLACK,
            ),
        )

    @classmethod
    def of(cls, problem: _Problem) -> _CompiledProblem | None:
        """The compiled search of ``problem``; None where numba is missing, its cache is
        not writable, the map is not a :class:`DrivableMap`, or ``RISKFLOW_COMPILED=0``."""
        if problem.map is not None and type(problem.map) is not DrivableMap:
            return None
        kernels = optional_kernels("policies.stress.escape_kernels", "the compiled escape search")
        return None if kernels is None else cls(problem, kernels)

    @staticmethod
    def _road(problem: _Problem) -> tuple:
        """(use_map, SDF raster, its int and float geometry, the footprint's offsets)."""
        along = 0.5 * problem.length * np.asarray(_ALONG)
        across = 0.5 * problem.width * np.asarray(_ACROSS)
        if problem.map is None:
            return (False, np.zeros(4), np.zeros((1, 3), np.int64), np.zeros((1, 4)), along, across)
        flat, grid_int, grid_float, _ = _map_tables(problem.map, (1,), 1)
        return (True, flat, grid_int, grid_float, along, across)

    def evaluate(self, knots: torch.Tensor, exact: bool = False) -> _Score:
        """:meth:`_Problem.evaluate` (without gradient); ``exact``: no pair skipped, so
        the least separation is exact too (module docstring of the kernels)."""
        rows = np.ascontiguousarray(knots.detach().numpy())
        states = np.empty((rows.shape[0], self.problem.horizon, 4))
        scores = np.empty((rows.shape[0], 4))
        self.kernels.score_rows(rows, *self.scene, exact, states, scores)
        cost, clear, worst, deepest = torch.from_numpy(scores).unbind(dim=1)
        feasible = (clear >= CLEARANCE) & (worst <= 0)
        return _Score(cost, feasible, torch.from_numpy(states), clear, deepest)

    def refine(self, knots: torch.Tensor) -> tuple[torch.Tensor, int]:
        """:meth:`_Problem.refine`."""
        rows = np.ascontiguousarray(knots.detach().numpy())
        search = self.problem.search
        steps = self.kernels.refine_rows(
            rows, self.low, self.high, search.steps, search.learning_rate, CLEARANCE, *self.scene
        )
        return torch.from_numpy(rows), int(steps)


def _interpolation(horizon: int, knot_steps: int) -> np.ndarray:
    """(H, K) weights: step t's action interpolates linearly between knots."""
    position = np.arange(horizon) / knot_steps
    knots = horizon // knot_steps + 2
    index = np.minimum(np.floor(position).astype(int), knots - 2)
    frac = position - index
    weights = np.zeros((horizon, knots))
    weights[np.arange(horizon), index] = 1.0 - frac
    weights[np.arange(horizon), index + 1] = frac
    return weights


__all__ = ["CLEARANCE", "Escape", "EscapeSearch", "Obstacles", "find_escape"]
