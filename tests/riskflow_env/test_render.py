"""SceneRenderer: map, vehicles, trails, event markers, overlays, human window."""

from __future__ import annotations

import re

import numpy as np
import pytest
import shapely

import riskflow_env
from riskflow_env import render
from riskflow_env.render import RenderConfig, SceneRenderer
from tests.riskflow_env.hand_made_scenes import make_env as hand_made_env

SCALE = 8.0  # [px/m] of the default view: 640 px for 80 m
ROAD = shapely.box(-60.0, -12.0, 120.0, 12.0)


def make_env(vehicles, render_mode=None, steps: int = 10):
    """Straight road y in [-12, 12] m; ``vehicles`` rows (x, y, v, yaw), the ego first."""
    env = hand_made_env(vehicles, steps, ROAD, render_mode, scenario_steps=steps, name="")
    env.reset(seed=0)
    return env


def pixel(x: float, y: float, ego=(0.0, 0.0)) -> tuple[int, int]:
    """(row, col) of world (x, y) [m] in a default frame centred on ``ego``."""
    return round(180 - (y - ego[1]) * SCALE), round(320 + (x - ego[0]) * SCALE)


def has_color(frame: np.ndarray, color) -> bool:
    return bool(np.all(frame == np.asarray(color, np.uint8), axis=-1).any())


def test_rgb_array_frame_shows_map_and_ego():
    env = make_env([(0.0, 0.0, 10.0, 0.0), (20.0, 4.0, 10.0, 0.0)], render_mode="rgb_array")
    frame = env.render()
    assert frame.shape == (360, 640, 3) and frame.dtype == np.uint8
    assert tuple(frame[pixel(-1.0, 0.0)]) == render.EGO  # the view is centred on the ego
    assert tuple(frame[pixel(19.0, 4.0)]) == render.OTHER
    assert tuple(frame[pixel(30.0, -6.0)]) == render.ROAD
    assert tuple(frame[pixel(30.0, 20.0)]) == render.OFFROAD
    env.close()


def test_view_follows_the_ego_and_trails_fade_in():
    env = make_env([(0.0, 0.0, 10.0, 0.0)], render_mode="rgb_array")
    for _ in range(5):
        env.step({"ego": np.zeros(2)})
    frame = env.render()
    assert tuple(frame[pixel(4.0, 0.0, ego=(5.0, 0.0))]) == render.EGO
    old, recent = frame[pixel(-12.0, 0.0, ego=(5.0, 0.0))], frame[pixel(0.0, 0.0, ego=(5.0, 0.0))]
    distance_to_ego = np.abs(np.array([old, recent], int) - render.EGO).sum(axis=-1)
    assert distance_to_ego[1] < distance_to_ego[0]  # the newer part of the trail is stronger
    assert tuple(old) != render.ROAD


def test_event_markers():
    env = make_env([(0.0, 0.0, 0.0, 0.0), (30.0, 0.0, 0.0, 0.0)], render_mode="rgb_array")
    assert not has_color(env.render(), render.COLLISION)
    collided = make_env([(0.0, 0.0, 0.0, 0.0), (3.0, 0.5, 0.0, 0.0)], render_mode="rgb_array")
    assert has_color(collided.render(), render.COLLISION)
    offroad = make_env([(0.0, 11.5, 0.0, 0.0)], render_mode="rgb_array")
    assert has_color(offroad.render(), render.OFFROAD_MARK)
    assert not has_color(env.render(), render.OFFROAD_MARK)


def test_overlays_and_highlights():
    env = make_env([(0.0, 0.0, 0.0, 0.0), (10.0, -4.0, 0.0, 0.0)])
    renderer = SceneRenderer("rgb_array")
    plans = np.zeros((2, 20, 2))
    plans[:, :, 0] = np.linspace(0.0, 30.0, 20)
    plans[:, :, 1] = [[6.0], [-8.0]]
    renderer.set_overlay("plans", plans, mask=[False, True], color=(1, 2, 3))
    renderer.set_overlay("set", plans, mask=[False, False], color=(4, 5, 6), highlight=["agent_1"])
    frame = renderer.render(env)
    assert tuple(frame[pixel(15.0, -8.0)]) == (1, 2, 3)
    assert tuple(frame[pixel(15.0, 6.0)]) != (1, 2, 3)  # masked out
    assert tuple(frame[pixel(10.0, -4.0 - 1.0 - 0.7)]) == (4, 5, 6)  # halo below agent_1
    renderer.clear_overlay("set")
    frame = renderer.render(env)
    assert has_color(frame, (1, 2, 3)) and not has_color(frame, (4, 5, 6))
    renderer.reset(env)
    assert not has_color(renderer.render(env), (1, 2, 3))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"trajectories": np.zeros((2, 5))}, "trajectories"),
        ({"trajectories": np.zeros((2, 5, 2)), "mask": np.ones(3, bool)}, "mask"),
        ({"trajectories": np.zeros((2, 5, 2)), "color": (0, 0, 300)}, "color"),
        ({"trajectories": np.zeros((2, 5, 2)), "width": 0}, "width"),
    ],
)
def test_overlay_validation(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SceneRenderer().set_overlay("bad", **kwargs)


def test_whole_map_view_and_config():
    env = make_env([(0.0, 0.0, 0.0, 0.0)])
    frame = SceneRenderer(config=RenderConfig(160, 90, follow_ego=False, show_text=False)).render(
        env
    )
    assert frame.shape == (90, 160, 3)
    assert tuple(frame[45, 8]) == render.ROAD and tuple(frame[2, 80]) == render.OFFROAD
    with pytest.raises(ValueError, match="width_px"):
        RenderConfig(width_px=0)
    with pytest.raises(ValueError, match="render_mode"):
        SceneRenderer("ansi")


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"width_px": 0}, "RenderConfig.width_px must be an int in [16, 8192]"),
        ({"width_px": 100_000}, "RenderConfig.width_px must be an int in [16, 8192]"),
        ({"height_px": 64.0}, "RenderConfig.height_px must be an int, got 64.0"),
        ({"view_width": 0.0}, "RenderConfig.view_width must be >= 0.001 m, got 0.0"),
        ({"view_width": np.nan}, "RenderConfig.view_width must be a finite number"),
        ({"trail_seconds": 10.0}, "RenderConfig.trail_seconds must be in [0, 3] s"),
        ({"trail_seconds": -0.1}, "RenderConfig.trail_seconds must be in [0, 3] s"),
    ],
)
def test_render_config_refuses_bad_values_when_built(changes, message):
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        RenderConfig(**changes)
    assert RenderConfig(trail_seconds=3.0).trail_seconds == 3.0  # the whole history


def test_human_mode_opens_a_window_and_closes_it():
    env = make_env([(0.0, 0.0, 10.0, 0.0)], render_mode="human", steps=2)
    assert env.render() is None
    env.step({"ego": np.zeros(2)})  # renders by itself in human mode
    assert render.pygame.display.get_surface() is not None
    env.close()
    assert not render.pygame.display.get_init()


def test_no_renderer_without_render_mode():
    env = make_env([(0.0, 0.0, 10.0, 0.0)])
    env.step({"ego": np.zeros(2)})
    assert env._renderer is None  # nothing drawn on the hot path


def test_collision_counter_counts_events_like_the_event_log():
    """A car drives through the standing ego (contact, then apart), then into a parked car:
    2 collision events, whatever is in contact on the last frame."""
    from riskflow_env.wrappers import EventLogWrapper

    vehicles = [(0.0, 0.0, 0.0, 0.0), (-10.0, 0.0, 20.0, 0.0), (12.0, 0.0, 0.0, 0.0)]
    env = EventLogWrapper(make_env(vehicles, render_mode="rgb_array", steps=12))
    env.reset(seed=0)
    base = env.unwrapped
    base.render()
    while env.agents:
        env.step({agent: np.zeros(2, np.float32) for agent in env.agents})
    summary = env.events[-1]
    assert summary["event"] == "episode_summary" and summary["collisions"] == 2
    assert base._renderer.collision_events == 2
    assert len(riskflow_env.events.contact_pairs(base.last_events.collisions)) == 1


def test_legend_names_the_labelled_overlays_on_the_frame():
    env = make_env([(0.0, 0.0, 0.0, 0.0), (10.0, -4.0, 0.0, 0.0)])
    renderer = SceneRenderer("rgb_array")
    plans = np.zeros((2, 20, 2))
    plans[:, :, 0] = np.linspace(0.0, 30.0, 20)
    renderer.set_overlay("a", plans, mask=[False, True], color=(1, 2, 3), label="base plans")
    renderer.set_overlay("b", plans, mask=[False, False], color=(4, 5, 6), label="guided plans")
    assert renderer.legend() == [
        ("base plans", (1, 2, 3)),  # "guided plans" has nothing to draw: not listed
        ("collision", render.COLLISION),
        ("off-road", render.OFFROAD_MARK),
    ]
    corner = renderer.render(env)[-80:, :60]  # the legend box, bottom left
    for color in ((1, 2, 3), render.COLLISION, render.OFFROAD_MARK):
        assert has_color(corner, color)
    renderer.clear_overlay("a")
    assert renderer.legend() == []  # no labelled overlay on the frame: no legend
