"""Regenerate ``docs/images/sample_frame.png``: ``python docs/images/make_sample_frame.py``.

A highway scene 1.2 s into a cut-in, with two overlays the way a scene policy pushes
them: every vehicle's straight 5 s plan (thin, grey) and the bent plans of a
"controllable" pair that cuts towards the ego (purple, haloed).
"""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np

import riskflow_env
from riskflow_env.config import EnvConfig
from riskflow_env.dynamics import rollout
from riskflow_env.render import RenderConfig, SceneRenderer
from riskflow_env.scenarios import HighwayTrafficSource, TrafficConfig

FRAME = Path(__file__).with_name("sample_frame.png")
PLAN_STEPS = 50  # 5 s at 10 Hz
DRIVEN = 12  # steps driven before the snapshot


def cut_in_actions(view, controllable: np.ndarray, steps: int) -> np.ndarray:
    """(A, steps, 2) actions: straight for all, a cut-in towards the ego's lane for some."""
    current = view.current
    actions = np.zeros((view.num_agents, steps, 2))
    toward_ego = np.sign(current[0, 1] - current[controllable, 1])[:, None]
    actions[controllable, :12, 1] = 0.12 * toward_ego  # steer in for 1.2 s,
    actions[controllable, 12:24, 1] = -0.12 * toward_ego  # then straighten
    actions[controllable, :, 0] = 1.5
    return actions


def main(path: Path = FRAME) -> None:
    traffic = TrafficConfig(families=("highway",), num_vehicles=(16, 16), radius=60.0)
    env = riskflow_env.parallel_env(
        config=EnvConfig(max_agents=16), scenarios=HighwayTrafficSource(traffic)
    )
    env.reset(seed=2)
    view = env.view()
    distance = np.linalg.norm(view.current[:, :2] - view.current[0, :2], axis=-1)
    distance[~view.present | (np.arange(view.num_agents) == 0)] = np.inf
    controllable = np.argsort(distance)[:2]  # stand-in for the ranked controllable set
    actions = cut_in_actions(view, controllable, PLAN_STEPS)
    for k in range(DRIVEN):  # drive into the manoeuvre
        env.step({agent: actions[view.slot(agent), k] for agent in env.agents})

    view = env.view()
    remaining = np.zeros_like(actions)
    remaining[:, : PLAN_STEPS - DRIVEN] = actions[:, DRIVEN:]
    renderer = SceneRenderer(
        "rgb_array", RenderConfig(width_px=640, height_px=360, view_width=60.0)
    )
    renderer.reset(env)
    renderer.set_overlay(
        "base plans",
        rollout(view.current, np.zeros_like(actions))[..., :2],
        mask=view.present,
        color=(215, 215, 215),
        width=1,
        label="straight plans",
    )
    mask = np.zeros(view.num_agents, bool)
    mask[controllable] = True
    renderer.set_overlay(
        "guided plans",
        rollout(view.current, remaining)[..., :2],
        mask=mask,
        color=(205, 90, 255),
        highlight=controllable.tolist(),
        label="guided plans (A_c, haloed)",
    )
    iio.imwrite(path, renderer.render(env))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
