"""Guidance test scenes: vehicles on a straight 12 m road whose base plans keep their
speed and heading (shared by the guidance tests of ``tests/policies/riskflow``)."""

from __future__ import annotations

import numpy as np
import torch

from policies.learned.data import ActionNormalizer
from policies.learned.sampler import decode_plans
from policies.riskflow.guidance import GuidanceScene
from riskflow_env.maps import Lane, from_lanes

NORMALIZER = ActionNormalizer(mean=(0.0, 0.0), std=(1.0, 0.1))
ROAD = from_lanes([Lane(np.array([[-100.0, 0.0], [300.0, 0.0]]), 12.0, "road")])  # |y| < 6 m
STEPS = 52


def make_scene(state: list[list[float]], frame=(0.0, 0.0, 0.0), seed: int = 0) -> GuidanceScene:
    """Vehicles (4.5 m x 2 m) whose base plans keep their speed and heading."""
    state = torch.tensor(state, dtype=torch.float32)
    num = state.shape[0]
    eps = torch.randn(num, STEPS, 2, generator=torch.Generator().manual_seed(seed))
    u0 = NORMALIZER.normalize(torch.zeros(num, STEPS, 2)) - eps  # keep speed and heading
    mask = torch.ones(num, dtype=torch.bool)
    actions, trajectories = decode_plans(eps + u0, state, mask, NORMALIZER)
    return GuidanceScene(
        eps=eps,
        u0=u0,
        state=state,
        length=torch.full((num,), 4.5),
        width=torch.full((num,), 2.0),
        agent_mask=mask,
        base_actions=actions,
        base_trajectories=trajectories,
        drivable_map=ROAD,
        frame=torch.tensor(frame),
    )


# Ego in the middle lane; others ahead and behind in the outer lanes, all at 15 m/s.
HIGHWAY = [
    [0.0, 0.0, 15.0, 0.0],
    [20.0, 3.5, 15.0, 0.0],
    [-15.0, -3.5, 15.0, 0.0],
    [35.0, -3.5, 15.0, 0.0],
    [-30.0, 3.5, 15.0, 0.0],
    [50.0, 0.0, 15.0, 0.0],
]


def mask_of(num: int, rows: list[int]) -> torch.Tensor:
    mask = torch.zeros(num, dtype=torch.bool)
    mask[rows] = True
    return mask
