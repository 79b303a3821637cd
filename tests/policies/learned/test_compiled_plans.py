"""The compiled avoidance steps (``policies.learned.compiled_plans``) give the reference
loop's plans: to 1e-9 on float64 scenes built to reach every branch (overlapping pairs,
the speed bounds, clipped actions, the map term off the road, a gain, exempt pairs,
scenes that stop at different steps), and to 1e-3 m on a planning cycle of the shipped
checkpoint with every default (float32 plans: the kernel computes in float64).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("numba")

from policies.learned import compiled_plans  # noqa: E402
from policies.learned.data import ActionNormalizer  # noqa: E402
from policies.learned.guidance_losses import MapTerm  # noqa: E402
from policies.learned.plan_avoidance import avoid_overlaps  # noqa: E402
from riskflow_env.config import DynamicsConfig  # noqa: E402
from riskflow_env.maps import MapStack  # noqa: E402
from tests.policies.riskflow.guidance_scenes import ROAD  # noqa: E402

NORMALIZER = ActionNormalizer(mean=(-0.1, 0.0), std=(1.5, 0.15))
DYNAMICS = DynamicsConfig()
SWITCH = "RISKFLOW_COMPILED"


def _random_scenes(num_scenes: int, num_agents: int, seed: int):
    """Crowded scenes on the 12 m road: agents within 25 m of each other, some at rest,
    some driving against the others, noise large enough to clip actions and brake to a
    standstill within the plan."""
    generator = torch.Generator().manual_seed(seed)

    def uniform(*shape, low=0.0, high=1.0):
        return low + (high - low) * torch.rand(*shape, generator=generator, dtype=torch.float64)

    state = torch.stack(
        [
            uniform(num_scenes, num_agents, high=25.0),
            uniform(num_scenes, num_agents, low=-7.0, high=7.0),
            uniform(num_scenes, num_agents, high=12.0),
            torch.where(uniform(num_scenes, num_agents) < 0.3, torch.pi, 0.0)
            + uniform(num_scenes, num_agents, low=-0.3, high=0.3),
        ],
        dim=-1,
    )
    state[:, -1, 2] = 0.0  # at rest: an obstacle
    length = uniform(num_scenes, num_agents, low=3.5, high=5.0)
    width = uniform(num_scenes, num_agents, low=1.6, high=2.1)
    mask = torch.ones(num_scenes, num_agents, dtype=torch.bool)
    mask[0, 1] = False
    eps = 1.5 * torch.randn(num_scenes, num_agents, 40, 2, generator=generator, dtype=torch.float64)
    u0 = 0.5 * torch.randn(eps.shape, generator=generator, dtype=torch.float64)
    return eps, u0, state, length, width, mask


def _map_term_of(length, width, num_scenes, stack: bool):
    frames = torch.tensor([[2.0, -1.0, 0.1]], dtype=torch.float64).expand(num_scenes, 3)
    maps = MapStack([ROAD] * num_scenes) if stack else ROAD
    num_agents = length.shape[1]

    def of(rows):
        scenes = rows // num_agents
        drivable_map = maps.select(scenes) if stack else maps
        return MapTerm(
            drivable_map, frames[scenes], length.flatten()[rows], width.flatten()[rows], 30,
            0.2, 0.98,
        )  # fmt: skip

    return of


def _both(monkeypatch, *args, **kwargs):
    """``avoid_overlaps`` on the reference loop, then on the compiled one."""
    results = []
    for switch in ("0", "1"):
        monkeypatch.setenv(SWITCH, switch)
        results.append(avoid_overlaps(*args, **kwargs))
    return results


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("with_map", ["none", "map", "stack"])
def test_compiled_steps_equal_the_reference(monkeypatch, seed, with_map):
    eps, u0, state, length, width, mask = _random_scenes(3, 7, seed)
    term = None if with_map == "none" else _map_term_of(length, width, 3, with_map == "stack")
    gain = torch.ones_like(eps[..., :1])
    gain[:, :, 0] = 0.5
    exempt = torch.zeros(3, 7, 7, dtype=torch.bool)
    exempt[:, 2, 3] = exempt[:, 3, 2] = True
    args = (eps, u0, state, length, width, mask, term, NORMALIZER, DYNAMICS)
    reference, compiled = _both(
        monkeypatch, *args, steps=25, step_size=0.15, gain=gain, exempt=exempt
    )
    assert not torch.equal(reference[0], u0)  # the steps moved the plans
    for want, got in zip(reference, compiled, strict=True):
        np.testing.assert_allclose(got.numpy(), want.numpy(), rtol=0, atol=1e-9)


def test_a_gain_over_every_step_and_a_map_term_of_another_length(monkeypatch):
    """A gain of one value per vehicle (B, A, 1, 1) broadcasts over the steps as in torch;
    a map term that scores fewer steps than the plans is an error that says so."""
    eps, u0, state, length, width, mask = _random_scenes(2, 5, 3)
    args = (eps, u0, state, length, width, mask)
    gain = torch.full((2, 5, 1, 1), 0.5, dtype=torch.float64)
    options = {"steps": 15, "step_size": 0.15, "gain": gain}
    reference, compiled = _both(monkeypatch, *args, None, NORMALIZER, DYNAMICS, **options)
    np.testing.assert_allclose(compiled[0].numpy(), reference[0].numpy(), rtol=0, atol=1e-9)
    term = _map_term_of(length, width, 2, stack=True)  # 30 steps
    monkeypatch.setenv(SWITCH, "1")
    with pytest.raises(ValueError, match="30 plan steps, the plans have 40"):
        avoid_overlaps(*args, term, NORMALIZER, DYNAMICS, steps=5, step_size=0.1, horizon=40)


def test_the_switch_and_what_the_kernel_takes(monkeypatch):
    moving = torch.zeros(2, 30, 2)
    monkeypatch.setenv(SWITCH, "1")
    assert compiled_plans.accepts(moving, None, NORMALIZER)
    monkeypatch.setenv(SWITCH, "0")
    assert not compiled_plans.accepts(moving, None, NORMALIZER)
    monkeypatch.setenv(SWITCH, "1")

    class Scaled(ActionNormalizer):  # a normaliser of its own: the reference decodes it
        pass

    assert not compiled_plans.accepts(moving, None, Scaled(mean=(0.0, 0.0), std=(1.0, 1.0)))
    length = torch.full((1, 2), 4.5, dtype=torch.float64)
    term = _map_term_of(length, length * 0.4, 1, stack=False)(torch.tensor([0, 1]))
    assert compiled_plans.accepts(moving, term, NORMALIZER)
    term.map = object()  # a lookup of its own
    assert not compiled_plans.accepts(moving, term, NORMALIZER)


def test_a_shipped_planning_cycle_agrees(monkeypatch):
    """The shipped checkpoint, every default of the unguided generator and of RiskFlow, a
    shipped scene of 20 vehicles whose avoidance runs every step: the plans of both loops."""
    import riskflow_env
    from policies.learned.windows import window_from_view
    from policies.registry import build_policy
    from riskflow_env.config import EnvConfig
    from riskflow_env.scenarios import shipped_bank

    env = riskflow_env.parallel_env(config=EnvConfig(max_agents=20))
    scenario = shipped_bank("eval")[2]
    env.reset(seed=0, options={"scenario": scenario})
    view = env.view()
    assert window_from_view(view).agent_mask.sum() >= 15
    corrections = []

    def recorded(*args, **kwargs):
        corrections.append(correct(*args, **kwargs))
        return corrections[-1]

    correct = compiled_plans.avoidance_correction
    monkeypatch.setattr(compiled_plans, "avoidance_correction", recorded)
    threads = torch.get_num_threads()
    try:
        for method in ("bits", "riskflow"):
            plans = []
            for switch in ("0", "1"):
                monkeypatch.setenv(SWITCH, switch)
                policy = build_policy(method, {}, k=5, planning_interval=0.5, target="ego", seed=0)
                policy.reset(view)
                plans.append(policy.plan(view))
            np.testing.assert_allclose(plans[1], plans[0], rtol=0, atol=1e-3, err_msg=method)
    finally:
        torch.set_num_threads(threads)
    assert len(corrections) == 2 and all(float(c.abs().max()) > 0.1 for c in corrections)


def _guidance_batch(dtype):
    """Three scenes of the guidance tests with their own maps and frames, padded to 6."""
    import dataclasses

    from policies.riskflow.guidance import GuidanceScene
    from riskflow_env.maps import Lane, from_lanes
    from tests.policies.riskflow.guidance_scenes import HIGHWAY, make_scene, mask_of
    from tests.policies.riskflow.test_guidance import _padded

    narrow = from_lanes([Lane(np.array([[-50.0, 10.0], [250.0, 40.0]]), 7.0, "narrow")])
    close = [[0.0, 0.0, 12.0, 0.0], [12.0, 2.5, 12.0, 0.1], [-9.0, -2.0, 14.0, 0.0]]
    scenes = [
        make_scene(HIGHWAY[:4], frame=(3.0, -1.0, 0.2), seed=1),
        make_scene(HIGHWAY, seed=2),
        dataclasses.replace(
            make_scene(close, frame=(-50.0, 10.0, 0.0997), seed=3), drivable_map=narrow
        ),
    ]
    padded = [_padded(s, 6) for s in scenes]
    names = ("eps", "u0", "state", "length", "width", "base_actions", "base_trajectories", "frame")
    batch = GuidanceScene(
        **{name: torch.stack([getattr(s, name) for s in padded]).to(dtype) for name in names},
        agent_mask=torch.stack([s.agent_mask for s in padded]),
        drivable_map=MapStack([s.drivable_map for s in scenes]),
    )
    controllable = [mask_of(4, [1, 3]), mask_of(6, [2, 4, 5]), mask_of(3, [1, 2])]
    masks = torch.stack([torch.cat([c, c.new_zeros(6 - len(c))]) for c in controllable])
    return batch, masks


GUIDED = [("others", 0.0, "adam"), ("ego", 50.0, "adam"), ("ego", 100.0, "gradient")]


@pytest.mark.parametrize(
    ("dtype", "target", "lambda_sep", "optimizer"),
    [(torch.float64, *case) for case in GUIDED] + [(torch.float32, *case) for case in GUIDED[:2]],
)
def test_compiled_guidance_equals_the_reference(monkeypatch, dtype, target, lambda_sep, optimizer):
    """Output-space guidance of three scenes in one loop (``L_adv``, ``L_map`` on two maps,
    ``L_sep`` with bystanders, the attacker's speed floor, Adam or plain steps): the
    compiled loop's plans and losses are the reference's. Plain steps of this size on
    float32 plans are not compared: their gradients (up to 3e4) make each step a jump to
    a bound, and the float32 reference itself moves by 0.05 from the float64 one."""
    from policies.riskflow.guidance import GuidanceConfig, guide
    from tests.policies.riskflow.guidance_scenes import NORMALIZER as GUIDANCE_NORMALIZER

    batch, masks = _guidance_batch(dtype)
    config = GuidanceConfig(
        steps=20, target=target, lambda_sep=lambda_sep, optimizer=optimizer, step_size=0.05
    )
    results = []
    for switch in ("0", "1"):
        monkeypatch.setenv(SWITCH, switch)
        results.append(guide(batch, masks, GUIDANCE_NORMALIZER, config))
    reference, compiled = results
    assert not torch.equal(reference.u, batch.u0)
    assert (reference.losses[0, :, 1] > 0).any()  # the map term is active somewhere
    tolerance = 1e-8 if dtype == torch.float64 else 1e-3
    for name in ("u", "actions", "trajectories", "losses"):
        np.testing.assert_allclose(
            getattr(compiled, name).numpy(), getattr(reference, name).numpy(),
            rtol=tolerance if name == "losses" else 0, atol=tolerance, err_msg=name,
        )  # fmt: skip


def test_one_guided_row_of_a_batch(monkeypatch):
    """One attacker in a batch of three scenes on their own maps (a selection of one map
    by a one-element index)."""
    from policies.riskflow.guidance import GuidanceConfig, guide
    from tests.policies.riskflow.guidance_scenes import NORMALIZER as GUIDANCE_NORMALIZER

    batch, masks = _guidance_batch(torch.float64)
    masks[:] = False
    masks[1, 2] = True
    results = []
    for switch in ("0", "1"):
        monkeypatch.setenv(SWITCH, switch)
        results.append(guide(batch, masks, GUIDANCE_NORMALIZER, GuidanceConfig(target="ego")))
    assert not torch.equal(results[0].u, batch.u0)
    np.testing.assert_allclose(results[1].u.numpy(), results[0].u.numpy(), rtol=0, atol=1e-8)


@pytest.mark.parametrize(
    ("module", "name", "called"),
    [("plan_kernels", "KERNELS_DIGEST", "riskflow_env/compiled_kernels.py"),
     ("plan_loops", "PIECES_DIGEST", "policies/learned/plan_kernels.py")],
)  # fmt: skip
def test_the_kernel_cache_sees_the_kernels_called_from_other_files(module, name, called):
    """numba's cache of a kernel module checks only its own source; the kernels it calls
    from another file are in it through that file's digest."""
    import hashlib
    import importlib
    from pathlib import Path

    root = Path(__file__).resolve().parents[3]
    source = (root / called).read_bytes().replace(b"\r\n", b"\n")
    digest = hashlib.sha256(source).hexdigest()
    kernels = importlib.import_module(f"policies.learned.{module}")
    assert getattr(kernels, name) == digest, f"{called} changed: set {module}.{name} = {digest!r}"


def test_no_writable_cache_directory(monkeypatch):
    """Where numba finds no writable cache directory, a warning names NUMBA_CACHE_DIR and
    the planning loops run the reference."""
    from tests.numba_cache import without_writable_cache

    without_writable_cache(
        monkeypatch, ("policies.learned.plan_loops", "policies.learned.plan_kernels")
    )
    monkeypatch.setenv(SWITCH, "1")
    compiled_plans.kernels.cache_clear()
    try:
        with pytest.warns(RuntimeWarning, match="NUMBA_CACHE_DIR"):
            assert not compiled_plans.accepts(torch.zeros(1, 30, 2), None)
    finally:
        monkeypatch.undo()
        compiled_plans.kernels.cache_clear()
    assert compiled_plans.accepts(torch.zeros(1, 30, 2), None)
