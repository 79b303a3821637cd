"""The policy tests' straight road and tiny generators, importable by any test module.

``make_road_scenario()``: six cars at 12 m/s along +x on a 12 m wide road (more cars
with ``extra``); ``road_env()`` is its env after a reset; ``run_closed_loop(policy,
steps)`` drives it with the ego holding its speed; ``perturbed_generator(seed)`` is a
tiny random generator whose plans depend on the noise and on the scene (the adaLN-Zero
head starts as ``u = 0``). The fixtures of ``tests/policies/conftest.py`` are built
from these.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

import riskflow_env
from policies.learned.config import ModelConfig
from policies.learned.data import ActionNormalizer
from policies.learned.generator import RiskFlowGenerator
from riskflow_env.config import EnvConfig
from riskflow_env.maps import Lane, from_lanes
from riskflow_env.scenarios import Scenario

TINY_MODEL = ModelConfig(
    encoder_dim=16, head_dim=32, context_dim=32, edge_dim=8, num_heads=2, encoder_layers=1,
    head_layers=1, map_widths=(4, 8), time_frequencies=8,
)  # fmt: skip
TINY_NORMALIZER = ActionNormalizer(mean=(0.0, 0.0), std=(0.5, 0.02))
ROAD_ENV = EnvConfig(
    max_agents=8, episode_steps=20, terminate_on_collision="all", terminate_on_offroad="none"
)
# (x [m], lane y [m]) at the current step, all at 12 m/s along +x; slot order = row order.
ROAD_START = [(0.0, 0.0), (18.0, 3.5), (-12.0, -3.5), (30.0, -3.5), (-25.0, 3.5), (45.0, 0.0)]


def perturbed_generator(seed: int) -> RiskFlowGenerator:
    """A tiny :data:`TINY_MODEL` generator, every parameter perturbed (frozen, eval mode)."""
    torch.manual_seed(seed)
    network = RiskFlowGenerator(TINY_MODEL)
    noise = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for param in network.parameters():
            param.add_(0.2 * torch.randn(param.shape, generator=noise))
    return network.eval().requires_grad_(False)


def make_road_scenario(extra: Sequence[tuple[float, float]] = ()) -> Scenario:
    """The cars of :data:`ROAD_START` (then ``extra``, same form) at 12 m/s along +x,
    31 history + 60 future steps."""
    road = from_lanes([Lane(np.array([[-150.0, 0.0], [500.0, 0.0]]), 12.0, "road")])
    starts = [*ROAD_START, *extra]
    steps, num = 31 + 60, len(starts)
    time = 0.1 * (np.arange(steps) - 30)
    states = np.zeros((num, steps, 4))
    for row, (x, y) in enumerate(starts):
        states[row, :, 0], states[row, :, 1], states[row, :, 2] = x + 12.0 * time, y, 12.0
    valid = np.ones(states.shape[:2], dtype=bool)
    return Scenario(road, states, valid, np.full(num, 4.5), np.full(num, 2.0), name="road")


def road_env(
    config: EnvConfig = ROAD_ENV, scenario: Scenario | None = None, seed: int | None = None
):
    """A ``riskflow_v0`` env reset on ``scenario`` (default the road) with ``seed``."""
    scenario = make_road_scenario() if scenario is None else scenario
    env = riskflow_env.parallel_env(config=config, scenarios=scenario)
    env.reset(seed=seed, options={"scenario": scenario})
    return env


def run_closed_loop(
    policy,
    steps: int,
    scenario: Scenario | None = None,
    config: EnvConfig = ROAD_ENV,
    hook: Callable | None = None,
):
    """``policy`` drives ``scenario`` (default the road) for ``steps`` steps with the ego
    holding its speed; ``hook(view, policy, actions)`` sees every step. Returns the env
    and the emitted actions per step."""
    env = road_env(config, scenario, seed=0)
    policy.reset(env.view())
    emitted = []
    for _ in range(steps):
        if not env.agents:
            break
        view = env.view()
        actions = policy.act(view)
        if hook is not None:
            hook(view, policy, actions)
        emitted.append(actions)
        env.step({**actions, "ego": np.zeros(2)} if "ego" in env.agents else actions)
    return env, emitted
