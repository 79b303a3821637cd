"""Logit-normal (t, r) sampling: ordering, logit moments, r = t rate, flow-matching mode,
the one-step share."""

from __future__ import annotations

import math

import pytest
import torch

from policies.riskflow.time_sampler import TimeSampler

N = 200_000


def _draw(sampler: TimeSampler, seed: int = 0):
    return sampler(N, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def test_times_are_ordered_inside_the_unit_interval():
    t, r = _draw(TimeSampler())
    assert t.shape == r.shape == (N,)
    assert bool((0 < t).all() and (t <= r).all() and (r < 1).all())


@pytest.mark.parametrize("mean, std", [(-0.4, 1.0), (0.5, 0.5)])
def test_logit_of_the_unsorted_pair_is_normal_with_the_configured_moments(mean, std):
    # Sorting permutes each pair, so t and r together are the 2N logit-normal draws.
    t, r = _draw(TimeSampler(mean=mean, std=std, equal_fraction=0.0))
    logits = torch.logit(torch.cat([t, r]))
    tolerance = 5 * std / math.sqrt(2 * N)
    assert abs(float(logits.mean()) - mean) < tolerance
    assert abs(float(logits.std()) - std) < 5 * std / math.sqrt(N)
    # The smaller of two draws: mean - std / sqrt(pi) for a normal.
    assert abs(float(torch.logit(t).mean()) - (mean - std / math.sqrt(math.pi))) < 3 * tolerance


@pytest.mark.parametrize("fraction", [0.0, 0.2, 0.75])
def test_r_equals_t_at_the_configured_rate(fraction):
    t, r = _draw(TimeSampler(equal_fraction=fraction))
    rate = float((r == t).double().mean())
    assert abs(rate - fraction) < 5 * math.sqrt(0.25 / N)


def test_flow_matching_mode_has_r_equal_t_and_logit_normal_t():
    t, r = _draw(TimeSampler(flow_matching=True))
    assert torch.equal(t, r)
    logits = torch.logit(t)
    assert abs(float(logits.mean()) + 0.4) < 5 / math.sqrt(N)
    assert abs(float(logits.std()) - 1.0) < 5 / math.sqrt(N)


def test_same_generator_seed_gives_the_same_times():
    first, second = _draw(TimeSampler(), seed=3), _draw(TimeSampler(), seed=3)
    assert all(torch.equal(a, b) for a, b in zip(first, second, strict=True))
    assert not torch.equal(first[0], _draw(TimeSampler(), seed=4)[0])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"std": 0.0}, "std"),
        ({"mean": math.nan}, "mean"),
        ({"equal_fraction": 1.5}, "equal_fraction"),
        ({"one_step_fraction": -0.1}, "one_step_fraction"),
        ({"one_step_fraction": 0.1, "flow_matching": True}, "one_step_fraction"),
    ],
)
def test_invalid_settings_are_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TimeSampler(**kwargs)


@pytest.mark.parametrize("fraction", [0.1, 0.5])
def test_one_step_share_is_the_samplers_own_call(fraction):
    t, r = _draw(TimeSampler(one_step_fraction=fraction))
    one_step = (t == 0) & (r == 1)
    assert abs(float(one_step.double().mean()) - fraction) < 5 * math.sqrt(0.25 / N)
    rest_t, rest_r = t[~one_step], r[~one_step]
    assert bool((0 < rest_t).all() and (rest_t <= rest_r).all() and (rest_r < 1).all())
    # The r = t share is drawn first and kept among the other pairs.
    rate = float((rest_r == rest_t).double().mean())
    assert abs(rate - 0.2) < 5 * math.sqrt(0.25 / len(rest_t))


def test_no_one_step_share_keeps_the_earlier_draws_bit_for_bit():
    assert all(
        torch.equal(a, b)
        for a, b in zip(
            _draw(TimeSampler(), seed=5),
            _draw(TimeSampler(one_step_fraction=0.0), seed=5),
            strict=True,
        )
    )
