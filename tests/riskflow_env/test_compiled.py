"""The compiled simulator step (riskflow_env.compiled) against the array-API reference:
same states, events, observations and rewards on random scenes; the switch and the
fallback."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import shapely
import torch

import riskflow_env
from riskflow_env import compiled, simulator
from riskflow_env.config import EnvConfig, ObservationConfig
from riskflow_env.geometry import footprint_points, separation
from riskflow_env.maps import MapStack, from_polygons
from riskflow_env.state import SceneState
from tests.numba_cache import without_writable_cache

needs_numba = pytest.mark.skipif(compiled.kernels() is None, reason="numba is not installed")
ROAD = from_polygons(  # the road along x leaves the map on the right (x = 65)
    [shapely.box(-40.0, -8.0, 60.0, 8.0), shapely.box(10.0, -40.0, 22.0, 40.0)],
    resolution=0.5,
    continuations=[shapely.box(60.0, -8.0, 80.0, 8.0)],
)
SMALL_ROAD = from_polygons([shapely.box(-20.0, -5.0, 20.0, 5.0)], resolution=0.25, margin=2.0)
CONFIG = EnvConfig(max_agents=8, terminate_on_offroad="all")
EPS = 1e-9  # [m] events are compared where the separation / SDF is farther than this from 0


def random_state(rng, lead: tuple, agents: int, spread: float = 30.0) -> SceneState:
    """Vehicles in clusters (so that some touch), some off the road or beyond the raster
    (the map spans about [-45, 65] x [-45, 45] m, its road along x going on past x = 65),
    random speeds, headings and masks."""
    shape = (*lead, agents)
    centres = rng.uniform(-spread, spread, (*lead, 1, 2))
    xy = centres + rng.normal(0.0, 4.0, (*shape, 2))
    xy[..., :1, :] += rng.choice([0.0, 80.0], (*lead, 1, 1))  # near or past the map edge
    current = np.concatenate(
        [xy, rng.uniform(0.0, 30.0, (*shape, 1)), rng.uniform(-4.0, 4.0, (*shape, 1))], axis=-1
    )
    present = rng.random(shape) < 0.85
    active = present & (rng.random(shape) < 0.8)
    return SceneState(
        history=np.stack([current - 1.0, current], axis=-2),
        history_valid=np.stack([present, present], axis=-1),
        length=rng.uniform(3.0, 6.0, shape),
        width=rng.uniform(1.5, 2.5, shape),
        present=present,
        active=active,
        last_action=rng.uniform(-6.0, 6.0, (*shape, 2)),
        step=3,
    )


def both_paths(monkeypatch, run):
    """``run()`` on the compiled path, then on the reference."""
    monkeypatch.setenv(compiled.SWITCH, "1")
    fast = run()
    monkeypatch.setenv(compiled.SWITCH, "0")
    slow = run()
    monkeypatch.delenv(compiled.SWITCH)
    return fast, slow


def assert_events_agree(state: SceneState, lookup, fast, slow) -> None:
    """Collision and off-road flags equal wherever the margin exceeds EPS."""
    current = state.current
    xy, yaw, length, width = current[..., :2], current[..., 3], state.length, state.width

    def pair(a):
        return a[..., :, None], a[..., None, :]

    xy_i, xy_j = xy[..., :, None, :], xy[..., None, :, :]
    (yaw_i, yaw_j), (len_i, len_j), (wid_i, wid_j) = pair(yaw), pair(length), pair(width)
    gap = separation(xy_i, yaw_i, len_i, wid_i, xy_j, yaw_j, len_j, wid_j)
    clear = np.abs(gap) > EPS
    np.testing.assert_array_equal(fast.collisions[clear], slow.collisions[clear])
    sdf = lookup.sdf_at(footprint_points(xy, yaw, length, width))  # (..., A, 9)
    clear = np.all(np.abs(sdf) > EPS, axis=-1)
    for name in ("offroad", "centroid_offroad"):
        np.testing.assert_array_equal(getattr(fast, name)[clear], getattr(slow, name)[clear])
    np.testing.assert_allclose(fast.offroad_fraction[clear], slow.offroad_fraction[clear])
    np.testing.assert_allclose(fast.sdf_depth, slow.sdf_depth, rtol=1e-12, atol=1e-9)


def assert_transitions_agree(state, lookup, fast, slow, observations: bool) -> None:
    (new_fast, report_fast), (new_slow, report_slow) = fast, slow
    np.testing.assert_allclose(new_fast.history, new_slow.history, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(new_fast.last_action, new_slow.last_action)
    evaluation_fast, evaluation_slow = report_fast.evaluation, report_slow.evaluation
    assert_events_agree(new_fast, lookup, evaluation_fast.events, evaluation_slow.events)
    np.testing.assert_array_equal(evaluation_fast.pair_mask, evaluation_slow.pair_mask)
    np.testing.assert_array_equal(new_fast.active, new_slow.active)
    np.testing.assert_array_equal(report_fast.terminated, report_slow.terminated)
    for name, term in evaluation_slow.reward_terms.items():
        np.testing.assert_allclose(evaluation_fast.reward_terms[name], term, atol=1e-9)
    np.testing.assert_allclose(report_fast.rewards, report_slow.rewards, atol=1e-9)
    if observations:
        np.testing.assert_allclose(
            evaluation_fast.pair_features, evaluation_slow.pair_features, atol=1e-9
        )
        assert report_fast.observations.dtype == np.float32
        np.testing.assert_allclose(
            report_fast.observations, report_slow.observations, rtol=1e-5, atol=1e-5
        )
    else:
        assert report_fast.observations is None and evaluation_fast.pair_features is None


@needs_numba
@pytest.mark.parametrize("observations", [True, False])
@pytest.mark.parametrize(
    ("lead", "agents", "spread"),
    [((), 1, 30.0), ((), 5, 10.0), ((), 32, 30.0), ((6,), 8, 20.0), ((2, 3), 12, 40.0)],
)
def test_random_scenes_agree_with_the_reference(monkeypatch, lead, agents, spread, observations):
    rng = np.random.default_rng(agents + 100 * len(lead))
    config = EnvConfig(
        max_agents=max(agents, 1),
        terminate_on_offroad="all",
        observation=ObservationConfig(num_neighbors=6, ray_directions=8),
    )
    for _ in range(5):
        state = random_state(rng, lead, agents, spread)
        actions = rng.uniform([-12.0, -1.5], [8.0, 1.5], (*lead, agents, 2))

        def run(state=state, actions=actions):
            return simulator.transition(state, actions, ROAD, config, observations=observations)

        fast, slow = both_paths(monkeypatch, run)
        assert_transitions_agree(state, ROAD, fast, slow, observations)


@needs_numba
def test_touching_boxes_and_map_edges(monkeypatch):
    """Boxes nose to tail, side by side and crossing; vehicles on the road edge and far
    beyond the raster; fewer neighbours than slots and more."""
    current = np.array(
        [
            [0.0, 0.0, 10.0, 0.0],
            [4.6, 0.0, 10.0, 0.0],  # 0.1 m behind nothing: gap to slot 0 is 0.1 m
            [0.0, 2.05, 5.0, 0.0],  # beside slot 0, 0.05 m apart
            [2.0, 0.5, 0.0, np.pi / 2],  # across slot 0: overlapping
            [59.0, 7.5, 3.0, 0.3],  # on the road edge
            [150.0, 120.0, 3.0, 1.0],  # far beyond the raster
            [-43.0, -44.0, 3.0, -2.0],  # near the raster corner
            [120.0, 2.0, 3.0, 0.1],  # on the road, 55 m past the raster's end
        ]
    )
    agents = len(current)
    present = np.ones(agents, dtype=bool)
    state = SceneState(
        history=current[:, None, :],
        history_valid=present[:, None],
        length=np.full(agents, 4.5),
        width=np.full(agents, 2.0),
        present=present,
        active=present.copy(),
        last_action=np.zeros((agents, 2)),
    )
    for neighbors in (0, 3, 12):
        config = EnvConfig(
            max_agents=agents, observation=ObservationConfig(num_neighbors=neighbors)
        )
        fast, slow = both_paths(monkeypatch, lambda c=config: simulator.evaluate(state, ROAD, c))
        np.testing.assert_array_equal(fast.events.collisions, slow.events.collisions)
        assert fast.events.collisions[0, 3] and not fast.events.collisions[0, 1]
        np.testing.assert_allclose(fast.observations, slow.observations, rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(fast.events.offroad, slow.events.offroad)
        assert fast.events.offroad[5] and fast.events.sdf_depth[5] > 50.0
        assert not fast.events.offroad[7] and fast.events.sdf_depth[7] < -3.0


@needs_numba
def test_a_map_per_scene(monkeypatch):
    """A batch looked up through a MapStack selection (SceneBatch's scenes of several
    maps) gives each scene its own map's values."""
    rng = np.random.default_rng(7)
    stack = MapStack([ROAD, SMALL_ROAD])
    lookup = stack.select(np.array([1, 0, 1, 1]))
    state = random_state(rng, (4,), 8, spread=15.0)
    actions = rng.uniform(-2.0, 2.0, (4, 8, 2))

    def run():
        return simulator.transition(state, actions, lookup, CONFIG)

    fast, slow = both_paths(monkeypatch, run)
    assert_transitions_agree(state, lookup, fast, slow, observations=True)
    alone = simulator.evaluate(fast[0], ROAD, CONFIG)  # scene 1 is on ROAD
    np.testing.assert_array_equal(alone.observations[1], fast[1].observations[1])


@needs_numba
def test_env_rollouts_agree_and_repeat(monkeypatch):
    """Same seed, same rollout on the compiled path (bit for bit); the reference's to
    float tolerance."""

    def rollout():
        env = riskflow_env.parallel_env(config=EnvConfig(max_agents=16, episode_steps=40))
        observations, _ = env.reset(seed=3)
        rng = np.random.default_rng(0)
        frames = [observations]
        while env.agents:
            actions = {agent: rng.uniform([-6.0, -0.8], [4.0, 0.8]) for agent in env.agents}
            observations, rewards, terminated, truncated, infos = env.step(actions)
            frames.append((observations, rewards, terminated, truncated))
        return frames, env.scene.history

    monkeypatch.delenv(compiled.SWITCH, raising=False)  # the default
    first, again = rollout(), rollout()
    np.testing.assert_array_equal(first[1], again[1])
    for one, other in zip(first[0][1:], again[0][1:], strict=True):
        assert one[1:] == other[1:]
        for agent, row in one[0].items():
            np.testing.assert_array_equal(row, other[0][agent])
    monkeypatch.setenv(compiled.SWITCH, "0")
    reference = rollout()
    np.testing.assert_allclose(first[1], reference[1], rtol=0.0, atol=1e-9)
    assert len(first[0]) == len(reference[0])
    for fast, slow in zip(first[0][1:], reference[0][1:], strict=True):
        assert fast[0].keys() == slow[0].keys() and fast[2] == slow[2] and fast[3] == slow[3]
        for agent, row in slow[0].items():
            np.testing.assert_allclose(fast[0][agent], row, rtol=1e-5, atol=1e-5)
            assert fast[1][agent] == pytest.approx(slow[1][agent], abs=1e-9)


def test_the_switch_and_the_fallbacks(monkeypatch):
    """RISKFLOW_COMPILED=0, a missing numba, torch tensors and float32 arrays all take
    the reference; it runs and gives float32 observations."""
    calls = []
    monkeypatch.setattr(compiled, "evaluate", lambda *args: calls.append(args))
    monkeypatch.setattr(compiled, "advance", lambda *args: calls.append(args))
    rng = np.random.default_rng(0)
    state = random_state(rng, (), 8)
    actions = np.zeros((8, 2))

    def step(state=state, actions=actions):
        return simulator.transition(state, actions, ROAD, CONFIG)[1].observations

    monkeypatch.setenv(compiled.SWITCH, "0")
    assert not compiled.enabled() and step().dtype == np.float32
    monkeypatch.setenv(compiled.SWITCH, "1")
    monkeypatch.setattr(compiled, "kernels", lambda: None)  # as without numba
    assert not compiled.enabled() and step().dtype == np.float32
    monkeypatch.undo()
    monkeypatch.setattr(compiled, "evaluate", lambda *args: calls.append(args))
    monkeypatch.setattr(compiled, "advance", lambda *args: calls.append(args))
    step(state.convert(torch.as_tensor), torch.zeros(8, 2, dtype=torch.float64))
    step(state.convert(lambda a: a.astype(np.float32) if a.dtype.kind == "f" else a))
    assert calls == []


@needs_numba
def test_numba_runs_by_default(monkeypatch):
    monkeypatch.delenv(compiled.SWITCH, raising=False)
    assert compiled.enabled()
    state = random_state(np.random.default_rng(1), (), 4)
    assert compiled.accepts_evaluate(state, ROAD)
    assert not compiled.accepts_evaluate(state, object())

    class OtherLookup(type(ROAD)):  # may look its SDF up otherwise: the reference
        pass

    other = OtherLookup(ROAD.drivable, ROAD.resolution, ROAD.origin, ROAD.sdf)
    assert not compiled.accepts_evaluate(state, other)
    current, present, actions = state.current, state.present, np.zeros((4, 2))
    assert compiled.accepts_advance(current, present, present, actions)
    assert not compiled.accepts_advance(current, present, present.astype(int), actions)


@needs_numba
def test_the_kernel_cache_sees_the_pair_kernels():
    """numba's cache of evaluate_scenes checks only compiled_kernels.py's source; the pair
    kernels it calls from compiled_pairs.py are in that source through PAIRS_DIGEST."""
    from riskflow_env import compiled_kernels, compiled_pairs

    source = Path(compiled_pairs.__file__).read_bytes().replace(b"\r\n", b"\n")
    digest = hashlib.sha256(source).hexdigest()
    assert digest == compiled_kernels.PAIRS_DIGEST, (
        f"compiled_pairs.py changed: set compiled_kernels.PAIRS_DIGEST = {digest!r}"
    )


@needs_numba
def test_no_writable_cache_directory(monkeypatch):
    """Where numba finds no writable cache directory (a read-only install, no writable
    home), a warning names NUMBA_CACHE_DIR and the reference runs."""
    without_writable_cache(
        monkeypatch, ("riskflow_env.compiled_kernels", "riskflow_env.compiled_pairs")
    )
    monkeypatch.setenv(compiled.SWITCH, "1")
    compiled.kernels.cache_clear()
    try:
        with pytest.warns(RuntimeWarning, match="NUMBA_CACHE_DIR"):
            assert not compiled.enabled()
        state = random_state(np.random.default_rng(2), (), 4)
        assert simulator.evaluate(state, ROAD, CONFIG).observations.dtype == np.float32
    finally:
        monkeypatch.undo()
        compiled.kernels.cache_clear()
    assert compiled.enabled()
