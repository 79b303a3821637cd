"""The escape search's compiled path (:mod:`policies.stress.escape_kernels`) against its
torch reference: the same scores, the same refinement steps, the same verdicts."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
import torch

from policies.stress import EscapeSearch, Obstacles, find_escape
from policies.stress import escape as escape_module
from riskflow_env import kernel_loading
from riskflow_env.compiled import SWITCH
from riskflow_env.config import DynamicsConfig
from riskflow_env.maps import from_polygons

pytest.importorskip("numba")

HORIZON = 40
ROAD = from_polygons(shapely.box(-40.0, -5.0, 120.0, 5.0), resolution=0.5)


SEARCH = EscapeSearch(samples=256, refine=8)


def crowded_problem(seed: int, drivable_map=ROAD, search=SEARCH):
    """A torch :class:`~policies.stress.escape._Problem` and its compiled twin: the ego at
    10 m/s among 8 vehicles on random straight tracks, some leaving the scene."""
    rng = np.random.default_rng(seed)
    count = 8
    origin = np.stack([rng.uniform(-20, 60, count), rng.uniform(-4, 4, count)], axis=-1)
    heading = rng.uniform(-0.5, 0.5, count) + np.where(rng.random(count) < 0.2, np.pi, 0.0)
    speed = rng.uniform(0, 15, count)
    time = np.arange(1, HORIZON + 1) * 0.1
    direction = np.stack([np.cos(heading), np.sin(heading)], axis=-1)
    xy = origin[:, None] + (speed[:, None] * time)[..., None] * direction[:, None]
    present = np.ones((count, HORIZON), dtype=bool)
    present[:3, 25:] = False
    obstacles = Obstacles(
        xy=xy,
        yaw=np.broadcast_to(heading[:, None], (count, HORIZON)).copy(),
        length=rng.uniform(3.5, 5.5, count),
        width=rng.uniform(1.6, 2.2, count),
        present=present,
    )
    start = np.array([0.0, 0.5, 10.0, 0.02])
    problem = escape_module._Problem(
        start, (4.5, 2.0), obstacles, drivable_map, DynamicsConfig(), search
    )
    compiled = escape_module._CompiledProblem.of(problem)
    assert compiled is not None
    return problem, compiled


@pytest.mark.parametrize("drivable_map", [ROAD, None], ids=["road", "no-map"])
@pytest.mark.parametrize("seed", [0, 1, 3])
def test_compiled_scores_equal_the_reference(seed, drivable_map):
    problem, compiled = crowded_problem(seed, drivable_map)
    knots = problem.sampled_knots(torch.Generator().manual_seed(seed))
    with torch.no_grad():
        reference = problem.evaluate(knots)
    exact = compiled.evaluate(knots, exact=True)
    for name in ("cost", "clearance", "road_depth", "states"):
        np.testing.assert_allclose(
            getattr(exact, name).numpy(), getattr(reference, name).numpy(), rtol=1e-9, atol=1e-9
        )
    assert torch.equal(exact.feasible, reference.feasible)
    assert 0 < int(reference.feasible.sum()) < len(knots)  # both verdicts are exercised
    # skipping the far pairs changes nothing but the least separation beyond the margin
    skipped = compiled.evaluate(knots)
    np.testing.assert_allclose(skipped.cost.numpy(), reference.cost.numpy(), rtol=1e-9, atol=1e-9)
    assert torch.equal(skipped.feasible, reference.feasible)
    near = reference.clearance <= escape_module.CLEARANCE + problem.search.margin
    np.testing.assert_allclose(skipped.clearance[near], reference.clearance[near], atol=1e-9)
    assert bool((skipped.clearance[~near] >= reference.clearance[~near] - 1e-9).all())


@pytest.mark.parametrize("seed", [1, 2])
def test_compiled_refinement_takes_the_reference_steps(seed):
    """Ten projected Adam steps from the same knots (infeasible ones, so no early stop)."""
    problem, compiled = crowded_problem(seed, search=EscapeSearch(refine=8, steps=10))
    knots = problem.sampled_knots(torch.Generator().manual_seed(seed))
    with torch.no_grad():
        score = problem.evaluate(knots)
    worst = knots[torch.argsort(score.cost, descending=True)[:8]]
    reference, steps = problem.refine(worst.clone())
    mine, compiled_steps = compiled.refine(worst.clone())
    assert steps == compiled_steps == 10
    assert not torch.equal(reference, worst)
    np.testing.assert_allclose(mine.numpy(), reference.numpy(), rtol=0, atol=1e-6)


@pytest.mark.parametrize("seed", range(4))
def test_both_paths_give_the_same_verdict(seed, monkeypatch):
    problem, _ = crowded_problem(seed)
    args = (
        problem.start.numpy(),
        (problem.length, problem.width),
        Obstacles(
            problem.xy.numpy(),
            problem.yaw.numpy(),
            problem.other_length.numpy(),
            problem.other_width.numpy(),
            problem.present.numpy(),
        ),
        ROAD,
        DynamicsConfig(),
        EscapeSearch(samples=64, refine=4, steps=30, seed=seed),
    )
    found = {}
    for switch in ("0", "1"):
        monkeypatch.setenv(SWITCH, switch)
        found[switch] = find_escape(*args)
    assert found["0"].found == found["1"].found
    assert found["0"].candidates == found["1"].candidates
    if found["0"].found:
        np.testing.assert_allclose(found["1"].states, found["0"].states, atol=1e-6)
        np.testing.assert_allclose(found["1"].actions, found["0"].actions, atol=1e-6)
        assert found["1"].clearance == pytest.approx(found["0"].clearance, abs=1e-6)


def test_the_kernel_cache_sees_the_pieces_it_calls():
    """numba's cache checks only the kernel module's own source; the planning pieces it
    calls are in it through their file's digest."""
    import hashlib
    from pathlib import Path

    from policies.stress import escape_kernels

    source = Path(__file__).resolve().parents[3] / "policies/learned/plan_kernels.py"
    digest = hashlib.sha256(source.read_bytes().replace(b"\r\n", b"\n")).hexdigest()
    assert escape_kernels.PIECES_DIGEST == digest, (
        f"plan_kernels.py changed: set escape_kernels.PIECES_DIGEST = {digest!r}"
    )


def test_no_writable_cache_directory_runs_the_reference(monkeypatch):
    """Where numba finds no writable cache directory, a warning names NUMBA_CACHE_DIR and
    the search runs the torch reference."""
    from tests.numba_cache import without_writable_cache

    problem, _ = crowded_problem(0)
    without_writable_cache(monkeypatch, ("policies.stress.escape_kernels",))
    monkeypatch.setenv(SWITCH, "1")
    kernel_loading._imported.cache_clear()
    try:
        with pytest.warns(RuntimeWarning, match="NUMBA_CACHE_DIR"):
            assert escape_module._CompiledProblem.of(problem) is None
    finally:
        monkeypatch.undo()
        kernel_loading._imported.cache_clear()
    assert escape_module._CompiledProblem.of(problem) is not None


@pytest.mark.parametrize("case", ["edge", "beside"])
def test_ties_share_the_gradient_as_autograd_does(case):
    """Exact ties (yaw 0 on an axis-aligned road: three footprint samples level with the
    edge; a same-size car alongside: equal SAT gaps) split the gradient in autograd; the
    kernels split it the same way, so the refinements stay equal."""
    horizon = 30
    time = np.arange(1, horizon + 1) * 0.1
    if case == "edge":  # the ego along the left road edge, a standing car ahead of it
        start, xy = (
            np.array([0.0, 3.9, 12.0, 0.0]),
            np.stack([np.full(horizon, 14.0), np.full(horizon, 3.9)], axis=-1),
        )
    else:  # a car of the same size alongside, as fast as the ego
        start, xy = (
            np.array([0.0, 0.0, 10.0, 0.0]),
            np.stack([4.55 + 10.0 * time, np.full(horizon, 1.0)], axis=-1),
        )
    obstacles = Obstacles(
        xy[None], np.zeros((1, horizon)), np.array([4.5]), np.array([2.0]),
        np.ones((1, horizon), dtype=bool),
    )  # fmt: skip
    search = EscapeSearch(samples=64, refine=4, steps=20)
    problem = escape_module._Problem(start, (4.5, 2.0), obstacles, ROAD, DynamicsConfig(), search)
    compiled = escape_module._CompiledProblem.of(problem)
    knots = problem.sampled_knots(torch.Generator().manual_seed(0))
    with torch.no_grad():
        worst = knots[torch.argsort(problem.evaluate(knots).cost, descending=True)[:4]]
    reference, steps = problem.refine(worst.clone())
    mine, compiled_steps = compiled.refine(worst.clone())
    assert steps == compiled_steps
    np.testing.assert_allclose(mine.numpy(), reference.numpy(), rtol=0, atol=1e-9)
