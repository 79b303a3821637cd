"""Avoidance steps (``avoid_steps``): the base plans' boxes are pulled apart, the ego's
and absent rows are not variables, and zero steps change nothing."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from policies.baselines.diffusion.sampling import OneCallSampler
from policies.baselines.nominal import NominalGenerator
from policies.learned.data import ActionNormalizer
from policies.learned.plan_avoidance import avoid_overlaps, guided_pairs
from policies.learned.plan_overlap import overlap_scores, pair_separation
from policies.learned.sampler import decode_plans
from policies.riskflow.policy import RiskFlowAdversary
from riskflow_env.config import DynamicsConfig
from riskflow_env.dynamics import rollout_with_vjp

NORMALIZER = ActionNormalizer(mean=(0.0, 0.0), std=(1.0, 0.1))
DYNAMICS = DynamicsConfig()
STEPS = 40  # plan steps


def _scene():
    """The ego far away, two cars 20 m apart driving at each other at 10 m/s (their boxes
    meet after about 0.8 s), an absent slot."""
    state = torch.tensor(
        [
            [
                [0.0, 50.0, 10.0, 0.0],
                [0.0, 0.0, 10.0, 0.0],
                [20.0, 0.0, 10.0, torch.pi],
                [0, 0, 0, 0],
            ]
        ],
        dtype=torch.float64,
    )
    length = torch.full((1, 4), 4.5, dtype=torch.float64)
    width = torch.full((1, 4), 1.8, dtype=torch.float64)
    mask = torch.tensor([[True, True, True, False]])
    eps = torch.zeros(1, 4, STEPS, 2, dtype=torch.float64)
    return eps, torch.zeros_like(eps), state, length, width, mask


def _overlap(trajectories, length, width, mask, state):
    return float(overlap_scores(trajectories[:, None, :, :30], length, width, mask, state).sum())


def test_steps_pull_the_boxes_apart():
    eps, u0, state, length, width, mask = _scene()
    _, trajectories = decode_plans(eps + u0, state, mask, NORMALIZER, DYNAMICS)
    before = _overlap(trajectories, length, width, mask, state)
    u, actions, after_plans = avoid_overlaps(
        eps, u0, state, length, width, mask, None, NORMALIZER, DYNAMICS, steps=30, step_size=0.2
    )
    after = _overlap(after_plans, length, width, mask, state)
    assert before > 1.0 and after < 0.1 * before
    assert torch.equal(u[:, 0], u0[:, 0]) and torch.equal(u[:, 3], u0[:, 3])  # ego, absent
    assert not torch.equal(u[:, 1], u0[:, 1]) and not torch.equal(u[:, 2], u0[:, 2])
    # the returned plans are the decoded u, as everywhere else
    expected = decode_plans(eps + u, state, mask, NORMALIZER, DYNAMICS)
    assert torch.equal(actions, expected[0]) and torch.equal(after_plans, expected[1])


def _autograd_steps(eps, u0, state, length, width, mask, steps, step_size, gain=1.0):
    """The steps as plain autograd through the whole decoding, torch.optim.Adam on every
    moving non-ego row (the correction times ``gain``): the reference of the closed-form
    steps."""
    variable = mask & (state[..., 2] > 0.2)
    variable[:, 0] = False
    delta = torch.zeros_like(u0, requires_grad=True)
    optimizer = torch.optim.Adam([delta], lr=step_size)
    for _ in range(steps):
        _, trajectories = decode_plans(
            eps + (u0 + gain * delta * variable[..., None, None]), state, mask, NORMALIZER, DYNAMICS
        )
        scored = trajectories[:, None, :, :30]
        loss = overlap_scores(scored, length, width, mask, state).sum()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return u0 + gain * delta.detach() * variable[..., None, None]


def test_closed_form_steps_agree_with_autograd():
    """The variables' rollout VJP in closed form and autograd only through the pairs'
    separation: the residuals of autograd through everything, to float rounding; a
    vehicle at rest is an obstacle, not a variable."""
    eps, u0, state, length, width, mask = _scene()
    state[0, 3] = torch.tensor([10.0, 1.5, 0.0, 0.0], dtype=torch.float64)  # at rest
    mask[0, 3] = True
    eps = 0.3 * torch.randn(eps.shape, generator=torch.Generator().manual_seed(0)).double()
    u, _, _ = avoid_overlaps(
        eps, u0, state, length, width, mask, None, NORMALIZER, DYNAMICS, steps=12,
        step_size=0.1, brake=False,
    )  # fmt: skip
    expected = _autograd_steps(eps, u0, state, length, width, mask, 12, 0.1)
    assert not torch.equal(u, u0)
    torch.testing.assert_close(u, expected, rtol=1e-9, atol=1e-9)
    assert torch.equal(u[:, 3], u0[:, 3])


def test_a_gain_blends_the_correction():
    """Blending first: the correction of each step times its gain (the new plan's share),
    scored on the plan that runs: autograd's steps through the gained correction; a gain
    of 0 keeps a step as it is."""
    eps, u0, state, length, width, mask = _scene()
    eps = 0.3 * torch.randn(eps.shape, generator=torch.Generator().manual_seed(1)).double()
    gain = torch.ones(1, 4, STEPS, 1, dtype=torch.float64)
    gain[..., :6, 0] = torch.linspace(0.0, 1.0, 8, dtype=torch.float64)[1:7]
    gain[:, 2, :3] = 0.0
    u, _, _ = avoid_overlaps(
        eps, u0, state, length, width, mask, None, NORMALIZER, DYNAMICS, steps=12,
        step_size=0.1, gain=gain, brake=False,
    )  # fmt: skip
    expected = _autograd_steps(eps, u0, state, length, width, mask, 12, 0.1, gain)
    torch.testing.assert_close(u, expected, rtol=1e-9, atol=1e-9)
    assert torch.equal(u[:, 2, :3], u0[:, 2, :3]) and not torch.equal(u[:, 2], u0[:, 2])
    ungained, _, _ = avoid_overlaps(
        eps, u0, state, length, width, mask, None, NORMALIZER, DYNAMICS, steps=12,
        step_size=0.1, brake=False,
    )  # fmt: skip
    # the first steps move less than without the gain
    assert (u - u0)[:, 1, 0].abs().sum() < (ungained - u0)[:, 1, 0].abs().sum()


def test_zero_steps_change_nothing():
    eps, u0, state, length, width, mask = _scene()
    u, actions, trajectories = avoid_overlaps(
        eps, u0, state, length, width, mask, None, NORMALIZER, DYNAMICS, steps=0, step_size=0.2
    )
    expected = decode_plans(eps + u0, state, mask, NORMALIZER, DYNAMICS)
    assert torch.equal(u, u0) and torch.equal(actions, expected[0])
    assert torch.equal(trajectories, expected[1])


def test_exempt_pairs_are_left_as_they_are():
    """The two cars drive at each other: exempting their pair (a controllable vehicle and
    its target) leaves both plans as they are; exempting another pair changes nothing."""
    eps, u0, state, length, width, mask = _scene()
    args = (eps, u0, state, length, width, mask, None, NORMALIZER, DYNAMICS)
    controllable = torch.tensor([[False, True, False, False]])
    targets = torch.tensor([[False, False, True, False]])
    exempt = guided_pairs(controllable, targets)
    assert exempt[0, 1, 2] and exempt[0, 2, 1] and int(exempt.sum()) == 2
    u, _, _ = avoid_overlaps(*args, steps=10, step_size=0.2, exempt=exempt)
    assert torch.equal(u, u0)
    other = guided_pairs(controllable, torch.tensor([[True, False, False, False]]))
    moved = avoid_overlaps(*args, steps=10, step_size=0.2, exempt=other)
    unexempt = avoid_overlaps(*args, steps=10, step_size=0.2)
    assert all(torch.equal(a, b) for a, b in zip(moved, unexempt, strict=True))


def _count_rollouts(monkeypatch) -> list:
    """A list that grows by one at each avoidance step (each rollout of the variables) of
    the reference loop (the compiled loop has its tests: test_compiled_plans.py)."""
    import policies.learned.plan_avoidance as avoidance

    monkeypatch.setenv("RISKFLOW_COMPILED", "0")
    calls = []

    def counted(*args, **kwargs):
        calls.append(1)
        return rollout_with_vjp(*args, **kwargs)

    monkeypatch.setattr(avoidance, "rollout_with_vjp", counted)
    return calls


def test_the_loop_stops_once_the_boxes_are_a_margin_apart(monkeypatch):
    """The two cars driving at each other: with many steps allowed, the loop stops at the
    first step without a gradient whose closest pair is ``STOP_MARGIN`` apart, and the
    plans it returns are those of that step."""
    import policies.learned.plan_avoidance as avoidance

    eps, u0, state, length, width, mask = _scene()
    calls = _count_rollouts(monkeypatch)
    args = (eps, u0, state, length, width, mask, None, NORMALIZER, DYNAMICS)
    _, _, plans = avoid_overlaps(*args, steps=500, step_size=0.2)
    assert 1 < len(calls) < 500
    gaps = pair_separation(plans[..., :30, :], length, width)[0, 1, 2]
    assert float(gaps.min()) >= avoidance.STOP_MARGIN


def test_nothing_to_correct_stops_after_the_first_gradient(monkeypatch):
    """Two cars side by side in their lanes, same speed: no overlap within the horizon, so
    the first gradient is zero and the loop stops there; the plans are those of zero
    steps, bit for bit (Adam's moments would stay zero)."""
    eps, u0, state, length, width, mask = _scene()
    state[0, 2] = torch.tensor([0.0, 4.0, 10.0, 0.0], dtype=torch.float64)
    calls = _count_rollouts(monkeypatch)
    args = (eps, u0, state, length, width, mask, None, NORMALIZER, DYNAMICS)
    gain = torch.ones_like(eps[..., :1])
    gain[:, :, 0] = 0.5  # blending first: half the first action's correction
    expected = avoid_overlaps(*args, steps=0, step_size=0.2)
    for options in ({}, {"gain": gain}):
        calls.clear()
        u, actions, trajectories = avoid_overlaps(*args, steps=10, step_size=0.2, **options)
        assert len(calls) == 1
        assert torch.equal(u, expected[0]) and torch.equal(actions, expected[1])
        assert torch.equal(trajectories, expected[2])


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"avoid_steps": -1}, "avoid_steps"),
        ({"avoid_steps": 1.5}, "avoid_steps"),
        ({"avoid_steps": True}, "avoid_steps"),
        ({"avoid_step_size": 0.0}, "avoid_step_size"),
        ({"avoid_step_size": float("nan")}, "avoid_step_size"),
        ({"avoid_step_size": True}, "avoid_step_size"),
    ],
)
def test_options_are_checked(tiny_meanflow, tiny_normalizer, options, match):
    models = {"generator": tiny_meanflow, "normalizer": tiny_normalizer}
    with pytest.raises(ValueError, match=match):
        RiskFlowAdversary(k=0, **models, **options)


def test_a_numpy_float_step_size_is_taken(tiny_meanflow, tiny_normalizer):
    models = {"generator": tiny_meanflow, "normalizer": tiny_normalizer}
    policy = RiskFlowAdversary(k=0, avoid_step_size=np.float32(0.1), **models)
    assert policy.avoid_step_size == 0.1 and type(policy.avoid_step_size) is float


def test_the_diffusion_generator_refuses_it(tiny_denoiser, tiny_normalizer):
    with pytest.raises(ValueError, match="avoid_steps > 0 needs the MeanFlow generator"):
        NominalGenerator(
            generator=OneCallSampler(tiny_denoiser, 3), normalizer=tiny_normalizer, avoid_steps=3
        )


def test_the_defaults_are_the_realistic_base(tiny_meanflow, tiny_denoiser, tiny_normalizer):
    """20 avoidance steps with MeanFlow (none with a diffusion generator, which has no
    one-step output to step on), holding at rest at 4 m and the map term weighted 20;
    ``riskflow-raw`` / ``bits-raw`` are the raw generator."""
    from policies.registry import build_policy

    meanflow = {"generator": tiny_meanflow, "normalizer": tiny_normalizer}
    for policy in (RiskFlowAdversary(k=5, **meanflow), NominalGenerator(**meanflow)):
        assert (policy.avoid_steps, policy.hold_distance) == (20, 4.0)
    assert RiskFlowAdversary(k=5, **meanflow).guidance.lambda_map == 20.0
    diffusion = {"generator": OneCallSampler(tiny_denoiser, 3), "normalizer": tiny_normalizer}
    assert NominalGenerator(**diffusion).avoid_steps == 0
    shared = {"k": 5, "planning_interval": 0.5, "target": "others", "seed": 0}
    plain = build_policy("riskflow-raw", meanflow, **shared)
    assert (plain.avoid_steps, plain.hold_distance, plain.guidance.lambda_map) == (0, 0.0, 20.0)
    raw = build_policy("bits-raw", meanflow, **shared)
    assert (raw.avoid_steps, raw.hold_distance) == (0, 0.0)


def test_closed_loop_with_avoidance_is_reproducible(tiny_meanflow, tiny_normalizer, closed_loop):
    """Same seed, same actions; on the conftest road, where no plans overlap and all stay
    on the road, the steps have nothing to do: the plans are those without them."""
    models = {"generator": tiny_meanflow, "normalizer": tiny_normalizer}
    runs = []
    for steps in (2, 2, 0):
        policy = NominalGenerator(planning_interval=0.3, seed=4, avoid_steps=steps, **models)
        _, emitted = closed_loop(policy, 7)  # three cycles
        runs.append(emitted)
    for first, other in ((runs[0], runs[1]), (runs[0], runs[2])):
        for ours, theirs in zip(first, other, strict=True):
            assert ours.keys() == theirs.keys()
            assert all(np.array_equal(ours[name], theirs[name]) for name in ours)


@pytest.mark.parametrize("target", ["ego", "others"])
def test_riskflow_leaves_the_guided_pairs_to_guidance(
    tiny_meanflow, tiny_normalizer, closed_loop, monkeypatch, target
):
    """The pairs of a vehicle of ``A_c`` and one of its targets are exempt from the
    avoidance steps (guidance decides them); with ``k = 0`` or without ``L_adv``
    nothing is."""
    import policies.pipeline.stages as riskflow

    seen = []

    def spy(*args, **kwargs):
        seen.append(kwargs["exempt"])
        return avoid_overlaps(*args, **kwargs)

    monkeypatch.setattr(riskflow, "avoid_overlaps", spy)
    models = {"generator": tiny_meanflow, "normalizer": tiny_normalizer}
    for k, lambda_adv in ((2, 1.0), (0, 1.0), (2, 0.0)):
        seen.clear()
        policy = RiskFlowAdversary(
            k=k, target=target, planning_interval=0.3, seed=1, lambda_adv=lambda_adv, **models
        )
        closed_loop(policy, 1)  # one cycle
        (exempt,) = seen
        if k == 0 or lambda_adv == 0:
            assert exempt is None
            continue
        controllable = torch.from_numpy(policy.ranking.controllable)[None]
        present = torch.ones_like(controllable)
        if target == "ego":
            targets = torch.zeros_like(controllable)
            targets[:, 0] = True
        else:
            targets = present & ~controllable
        assert controllable.sum() == (1 if target == "ego" else 2)  # "ego": one attacker
        assert torch.equal(exempt, guided_pairs(controllable, targets))


def test_a_batch_drops_each_scene_when_it_stops(monkeypatch):
    """Three scenes in one call (the two cars head-on 20 m apart; side by side, nothing to
    correct; head-on 30 m apart near the road's edge, with the map term): each scene's
    plans are those it gets alone, and a scene's rows leave the loop when it stops (the
    rollouts shrink), so the call runs as many steps as its longest scene."""
    from policies.learned.guidance_losses import MapTerm
    from tests.policies.riskflow.guidance_scenes import ROAD

    parts = [_scene() for _ in range(3)]
    parts[1][2][0, 2] = torch.tensor([0.0, 4.0, 10.0, 0.0], dtype=torch.float64)
    parts[2][2][0, 1:3, 1] = 3.5
    parts[2][2][0, 2, 0] = 30.0
    eps, u0, state, length, width, mask = (
        torch.cat([part[i] for part in parts]) for i in range(6)
    )  # fmt: skip
    gain = torch.ones_like(eps[..., :1])
    gain[:, 1:3, 0] = 0.5

    def map_term_of(length, width):
        def of(rows):
            frame = torch.zeros(3, dtype=torch.float64)
            return MapTerm(ROAD, frame, length.flatten()[rows], width.flatten()[rows], 30, 0.2, 0.9)

        return of

    rows_per_call = []
    monkeypatch.setenv("RISKFLOW_COMPILED", "0")  # the reference loop (test_compiled_plans.py)

    def counted(now, *args, **kwargs):
        rows_per_call.append(now.shape[0])
        return rollout_with_vjp(now, *args, **kwargs)

    import policies.learned.plan_avoidance as avoidance

    monkeypatch.setattr(avoidance, "rollout_with_vjp", counted)
    options = {"steps": 60, "step_size": 0.2}
    alone, calls = [], []
    for index in range(3):
        part = [t[index : index + 1] for t in (eps, u0, state, length, width, mask)]
        term = map_term_of(part[3], part[4])
        rows_per_call.clear()
        alone.append(
            avoid_overlaps(
                *part[:6], term, NORMALIZER, DYNAMICS, gain=gain[index : index + 1], **options
            )
        )
        calls.append(len(rows_per_call))
    rows_per_call.clear()
    term = map_term_of(length, width)
    batched = avoid_overlaps(
        eps, u0, state, length, width, mask, term, NORMALIZER, DYNAMICS, gain=gain, **options
    )
    assert calls[1] == 1 and calls[0] != calls[2] and max(calls) > 2
    assert len(rows_per_call) == max(calls)
    assert rows_per_call[0] == 6 and rows_per_call[1] == 4 and rows_per_call[-1] == 2
    for index, expected in enumerate(alone):
        for got, want in zip(batched, expected, strict=True):
            np.testing.assert_allclose(got[index : index + 1], want, rtol=0, atol=1e-9)
