"""Closed-loop training scenes: the generator drives a recorded scene, then learns to return.

A generator trained on logged windows only sees histories that the log drove; in closed
loop each plan starts where its own earlier plans left the scene, and small errors add
up (docs/REALISM.md). Recovery windows (:mod:`policies.learned.recovery`) perturb the log
with hand-made bumps; this module instead puts the generator's *own* closed-loop states
into the training data, as CAT-K does for the WOSAC leaders (Zhang et al. 2025, "Closest
Among Top-K: closed-loop supervised fine-tuning of behavior models", CVPR: roll the
policy out, at each step execute the one of its top-K candidates closest to the log,
and train on the states reached with targets that lead back to the log).

Here, for one recorded scene:

1. **Drive.** From the scene's current step every agent of the window is driven by the
   generator, re-planning every ``interval`` steps, as in the evaluation. Each cycle draws
   ``candidates`` joint plans in one batched pass and executes, per agent, the plan
   whose first ``interval`` positions are closest to the log (squared error over the
   steps the log holds). Agents that the log does not hold over the whole cycle, and
   those outside the window, follow the log.
2. **Targets.** Every ``every`` cycles the scene is cut into a training scene of
   ``history_steps + future_steps`` steps whose current step is the reached one: its
   history is the closed-loop history, and its future is the unicycle rollout of the
   *return actions* of each agent of the window: the actions, within the dynamics'
   bounds, that minimise ``sum_j w_j (e_across_j^2 + alpha e_along_j^2 + beta (v_j -
   v_log_j)^2) + lambda sum_j |c_j / s|^2 + mu sum_j |(c_j - c_{j-1}) / s|^2``: ``e`` is
   the offset from the logged position at step ``j``, split across and along the logged
   heading, ``c = a - a_log`` the correction of the log's own actions, ``s = (1 m/s^2,
   0.1 rad/s)`` and ``w_j = min(1, (j + 1) / R)^2``. The agent returns to its logged path
   over about ``R`` steps (``return_steps``), smoothly, without racing to catch up with
   where the log is (``alpha`` small), and keeps the log's own accelerations and turns
   where it is on the log already. Solved with projected Adam, all agents and windows at
   once. ``supervised_steps`` keeps only the first steps of each return plan as the
   target (the rest of the future is marked invalid), CAT-K's short horizon.

docs/REALISM.md (round 7) has what fine-tuning on these scenes did: 5 s returns whose
speed comes from the log made the traffic collide more; the first second alone did not
harm the open-loop accuracy but did not reduce collisions either.

The training scenes are ordinary scenes (``riskflow_env.scenarios.io``): ``riskflow-train
--data`` reads their folder beside the recorded ones, and each yields exactly one window
(its current step is the only one with a full history and future), whose actions
(:func:`riskflow_env.dynamics.inverse` of its states) are the return actions.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch

from policies.learned.data import Normalizer
from policies.learned.generator import RiskFlowGenerator
from policies.learned.sampler import sample
from policies.learned.window_types import Window, collate_windows
from policies.learned.windows import WindowConfig, build_window, scene_to_world, select_rows
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import SPEED, YAW, clip_actions, rollout, wrap_angle
from riskflow_env.scenarios.scenario import Scenario

ACTION_SCALE = (1.0, 0.1)
"""``s``: the return objective's unit of acceleration [m/s^2] and yaw rate [rad/s]"""


@dataclass(frozen=True)
class ClosedLoopConfig:
    """How closed-loop training scenes are driven and cut (module docstring)."""

    candidates: int = 4
    """joint plans drawn per cycle; each vehicle executes the one closest to its log"""
    interval: int = 5
    """steps executed per cycle (the evaluation re-plans every 5 steps, 0.5 s)"""
    cycles: int = 9
    """cycles driven per scene at most (fewer where the scene's log ends)"""
    every: int = 2
    """a training scene is cut every this many cycles"""
    return_steps: int = 20
    """R: steps over which the return target reaches full weight"""
    along_weight: float = 0.1
    """weight of the offset along the logged heading (across it weighs 1): a vehicle that
    fell behind its log need not race to catch up"""
    speed_weight: float = 0.5
    """weight [s^2] of the squared speed error to the log's"""
    deviation_weight: float = 0.01
    """lambda: weight of the correction's size"""
    smooth_weight: float = 1.0
    """mu: weight of the correction's step-to-step change"""
    iterations: int = 200
    """Adam steps of the return objective"""
    learning_rate: float = 0.05
    """Adam step size, in units of s = (1 m/s^2, 0.1 rad/s)"""
    supervised_steps: int = 0
    """steps of each return plan kept as the target (the rest of the future is marked
    invalid, so training supervises the first steps alone, as CAT-K supervises the next
    token); 0: the whole plan"""
    seed: int = 0
    """seed of the plans' noise (scene i of a run draws from (seed, i))"""

    def __post_init__(self) -> None:
        for name in ("candidates", "interval", "cycles", "every", "return_steps", "iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"ClosedLoopConfig.{name} must be an int >= 1, got {value!r}")
        for name in ("along_weight", "speed_weight", "deviation_weight", "smooth_weight"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(f"ClosedLoopConfig.{name} must be a number >= 0, got {value!r}")
        rate = self.learning_rate
        if not isinstance(rate, (int, float)) or not math.isfinite(rate) or rate <= 0:
            raise ValueError(f"ClosedLoopConfig.learning_rate must be a number > 0, got {rate!r}")
        steps = self.supervised_steps
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 0:
            raise ValueError(
                f"ClosedLoopConfig.supervised_steps must be an int >= 0, got {steps!r}"
            )
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise ValueError(f"ClosedLoopConfig.seed must be an int, got {self.seed!r}")


def _to_world(scene: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """``(..., 4)`` scene-frame states of the frame ``pose`` (x, y, v, psi) in the world,
    headings wrapped (scene files hold wrapped headings)."""
    world = scene_to_world(scene, pose[[0, 1, YAW]])
    world[..., YAW] = wrap_angle(world[..., YAW])
    return world


def _window(tracks: np.ndarray, scenario: Scenario, current: int, config: WindowConfig) -> Window:
    moved = dataclasses.replace(scenario, states=tracks)
    rows = select_rows(moved, current, config)
    return build_window(
        tracks, scenario.valid, scenario.length, scenario.width, scenario.map, rows, current, config
    )


@torch.no_grad()
def drive(
    scenario: Scenario,
    model: RiskFlowGenerator,
    normalizer: Normalizer,
    window_config: WindowConfig,
    config: ClosedLoopConfig,
    generator: torch.Generator,
) -> tuple[np.ndarray, list[tuple[int, Window, np.ndarray]]]:
    """Step 1 of the module docstring: the scene driven in closed loop.

    Returns:
        the driven ``(N, T, 4)`` tracks (the log after the last cycle), and for every
        ``every``-th cycle ``(current step, window at it, history tracks)``: the window's
        history is the closed-loop one and its future the log's; ``history tracks`` is
        ``(N, history_steps, 4)``, every agent's states up to that step.
    """
    device = next(model.parameters()).device
    tracks = scenario.states.astype(np.float64)  # a copy
    valid = scenario.valid
    history, future = window_config.history_steps, window_config.future_steps
    last = tracks.shape[1] - future - 1  # the last current step with a whole future
    now, cut = scenario.current_index, []
    for cycle in range(1, config.cycles + 1):
        if now + config.interval > last or not valid[scenario.ego_index, now]:
            break
        window = _window(tracks, scenario, now, window_config)
        batch = collate_windows([window]).to(device)
        _, plans = sample(
            model, batch, None, normalizer, num_samples=config.candidates,
            generator=generator, dynamics=window_config.dynamics,
        )  # fmt: skip
        plans = plans[0, :, :, : config.interval].double().cpu().numpy()  # (K, A, I, 4)
        logged = window.future[:, : config.interval]
        held = window.future_valid[:, : config.interval].all(axis=1)  # (A,)
        error = ((plans[..., :2] - logged[..., :2]) ** 2).sum(axis=(-1, -2))  # (K, A)
        chosen = plans[error.argmin(axis=0), np.arange(plans.shape[1])]  # (A, I, 4)
        world = _to_world(chosen, tracks[window.agent_index[0], now])
        rows = window.agent_index[held]
        tracks[rows, now + 1 : now + 1 + config.interval] = world[held]
        now += config.interval
        if cycle % config.every == 0 and valid[scenario.ego_index, now]:
            window = _window(tracks, scenario, now, window_config)
            cut.append((now, window, tracks[:, now - history + 1 : now + 1].copy()))
    return tracks, cut


def return_actions(
    windows: list[Window], dynamics: DynamicsConfig, config: ClosedLoopConfig
) -> list[np.ndarray]:
    """Step 2 of the module docstring: each window's return plan.

    Args:
        windows: windows with future fields whose history ends off the log and whose
            future is the log's.
        dynamics: bounds and time step.
        config: the objective's weights and the solver's steps.

    Returns:
        per window, ``(A, F, 4)`` float64 scene-frame states of the return plan (the
        rollout of its actions from the current state).
    """
    batch = collate_windows(windows).map(lambda t: t.double() if t.is_floating_point() else t)
    state = batch.history[:, :, -1]  # (B, A, 4)
    logged, held = batch.future, batch.future_valid  # (B, A, F, 4), (B, A, F)
    log_actions = torch.where(batch.actions_valid[..., None], batch.actions, 0.0)
    log_actions = torch.cat([log_actions[..., 1:2, :], log_actions[..., 1:, :]], dim=-2)
    log_actions = clip_actions(log_actions, dynamics)  # the first step's is the second's
    scale = torch.tensor(ACTION_SCALE, dtype=state.dtype)
    steps = torch.arange(logged.shape[-2], dtype=state.dtype)
    weight = ((steps + 1) / config.return_steps).clamp(max=1.0) ** 2 * held
    cos, sin = torch.cos(logged[..., YAW]), torch.sin(logged[..., YAW])
    correction = torch.zeros_like(log_actions, requires_grad=True)
    optimiser = torch.optim.Adam([correction], lr=config.learning_rate)
    for _ in range(config.iterations):
        actions = clip_actions(log_actions + correction * scale, dynamics)
        states = rollout(state, actions, dynamics, clip=False)
        offset = states[..., :2] - logged[..., :2]
        along = offset[..., 0] * cos + offset[..., 1] * sin
        across = offset[..., 1] * cos - offset[..., 0] * sin
        speed = states[..., SPEED] - logged[..., SPEED]
        position = across**2 + config.along_weight * along**2 + config.speed_weight * speed**2
        change = correction[..., 1:, :] - correction[..., :-1, :]
        loss = (
            (weight * position).sum()
            + config.deviation_weight * (correction**2).sum()
            + config.smooth_weight * (change**2).sum()
        )
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        actions = clip_actions(log_actions + correction * scale, dynamics)
        states = rollout(state, actions, dynamics, clip=False).numpy()
    return [states[i, : w.num_agents] for i, w in enumerate(windows)]


def closed_loop_scenes(
    scenario: Scenario,
    model: RiskFlowGenerator,
    normalizer: Normalizer,
    window_config: WindowConfig,
    config: ClosedLoopConfig,
    position: int = 0,
) -> list[Scenario]:
    """The training scenes of ``scenario`` (module docstring): one per cut.

    Args:
        scenario: a recorded scene (its current step starts the drive).
        model, normalizer: the generator that drives (in ``eval()`` mode).
        window_config: the training windows' sizes (those of ``riskflow-train``).
        config: the drive and the return objective.
        position: the scene's position in its folder (its noise draws from ``(seed,
            position)``).

    Returns:
        scenes of ``history_steps + future_steps`` steps each (their current step is
        the reached one); empty where the scene is too short for one cycle.
    """
    device = next(model.parameters()).device
    generator = torch.Generator(device=device)
    generator.manual_seed(int(np.random.SeedSequence([config.seed, position]).generate_state(1)[0]))
    _, cut = drive(scenario, model, normalizer, window_config, config, generator)
    if not cut:
        return []
    plans = return_actions([window for _, window, _ in cut], window_config.dynamics, config)
    history, future = window_config.history_steps, window_config.future_steps
    scenes = []
    for (now, window, past), plan in zip(cut, plans, strict=True):
        span = slice(now - history + 1, now + future + 1)
        states = np.concatenate([past, scenario.states[:, now + 1 : span.stop]], axis=1)
        states = states.astype(np.float64)
        rows, held = window.agent_index, window.future_valid
        world = _to_world(plan, past[rows[0], -1])  # (A, F, 4)
        future_part = states[rows, history:]
        states[rows, history:] = np.where(held[..., None], world, future_part)
        valid = scenario.valid[:, span].copy()
        if config.supervised_steps:
            valid[rows, history + config.supervised_steps :] = False
        scenes.append(
            dataclasses.replace(
                scenario,
                states=np.where(valid[..., None], states, 0.0),
                valid=valid,
                history_steps=history,
                name=f"{scenario.name}-closed-loop-{now}",
                source=f"{scenario.source}+closed-loop" if scenario.source else "closed-loop",
            )
        )
    return scenes


__all__ = ["ACTION_SCALE", "ClosedLoopConfig", "closed_loop_scenes", "drive", "return_actions"]
