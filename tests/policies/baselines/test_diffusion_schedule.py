"""DDPM schedule and DDIM transitions against closed-form answers (toy denoisers)."""

from __future__ import annotations

import math

import pytest
import torch

from policies.baselines.diffusion.sampling import chain_noise, reverse_chain
from policies.baselines.diffusion.schedule import DiffusionSchedule, ScheduleConfig


class GaussianDenoiser:
    """The exact posterior-mean denoiser of data ``x0 ~ N(mean, std^2)`` (per entry).

    ``E[x0 | x_k] = mean + std^2 sqrt(ab) / (ab std^2 + 1 - ab) (x_k - sqrt(ab) mean)``.
    """

    def __init__(self, schedule: DiffusionSchedule, mean: float, std: float) -> None:
        self.schedule, self.mean, self.std = schedule, mean, std

    def __call__(self, x_k, k, scene, *, clip=False):
        alpha_bar = float(self.schedule.alpha_bar[k])
        gain = self.std**2 * math.sqrt(alpha_bar) / (alpha_bar * self.std**2 + 1 - alpha_bar)
        x0 = self.mean + gain * (x_k - math.sqrt(alpha_bar) * self.mean)
        return x0, self.schedule.eps_from_x0(x_k, k, x0)


@pytest.mark.parametrize("kind", ["cosine", "linear"])
def test_forward_marginals_match_the_one_step_chain(kind):
    """q(x_k | x_0) closed form == the product of the K one-step kernels q(x_j | x_{j-1})."""
    schedule = DiffusionSchedule(ScheduleConfig(kind=kind))
    scale, variance = torch.tensor(1.0, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64)
    for k in range(schedule.num_steps):
        scale = scale * schedule.alphas[k].sqrt()
        variance = schedule.alphas[k] * variance + schedule.betas[k]
        mean_scale, std = schedule.q_moments(k, torch.zeros(1, dtype=torch.float64))
        torch.testing.assert_close(mean_scale[0], scale)
        torch.testing.assert_close(std[0] ** 2, variance)
    assert bool((schedule.betas > 0).all()) and bool((schedule.betas <= 0.999).all())
    assert float(schedule.alpha_bar[-1]) < 1e-3 < float(schedule.alpha_bar[0])


def test_q_sample_moments_empirically():
    schedule = DiffusionSchedule()
    gen = torch.Generator().manual_seed(0)
    x0 = torch.full((200_000,), 1.5, dtype=torch.float64)
    for k in (0, 30, 70, 99):
        noise = torch.randn(x0.shape, generator=gen, dtype=torch.float64)
        x_k = schedule.q_sample(x0, k, noise)
        alpha_bar = float(schedule.alpha_bar[k])
        assert abs(float(x_k.mean()) - 1.5 * math.sqrt(alpha_bar)) < 0.01
        assert abs(float(x_k.std()) - math.sqrt(1 - alpha_bar)) < 0.01


def test_ddim_eta1_on_consecutive_levels_is_the_ddpm_posterior():
    schedule = DiffusionSchedule()
    gen = torch.Generator().manual_seed(1)
    x0, x_k = torch.randn(2, 5, 3, generator=gen, dtype=torch.float64)
    for k in range(schedule.num_steps):
        eps = schedule.eps_from_x0(x_k, k, x0)
        torch.testing.assert_close(schedule.x0_from_eps(x_k, k, eps), x0)
        mean, sigma = schedule.reverse_moments(x0, eps, k, k - 1, eta=1.0)
        post_mean, post_var = schedule.posterior(x0, x_k, k)
        torch.testing.assert_close(mean, post_mean)
        assert math.isclose(sigma**2, float(post_var), rel_tol=1e-9, abs_tol=1e-15)


def test_ddim_with_every_level_and_eta1_follows_the_ddpm_path():
    schedule = DiffusionSchedule()
    denoiser = GaussianDenoiser(schedule, mean=0.7, std=0.3)
    levels = schedule.levels()
    assert levels == schedule.levels(schedule.num_steps)
    noise = chain_noise((64,), levels, torch.Generator().manual_seed(2), dtype=torch.float64)
    path = reverse_chain(denoiser, None, noise, levels, eta=1.0)
    x = noise[0]
    for index, (k, _) in enumerate(levels):  # Ho et al. 2020, algorithm 2
        mean, variance = schedule.posterior(denoiser(x, k, None)[0], x, k)
        x = mean + variance.sqrt() * noise[index + 1]
        torch.testing.assert_close(path[index + 1], x)


@pytest.mark.parametrize(
    ("num_steps", "steps", "eta", "std_error"),
    [
        (100, None, 1.0, 0.025),
        (1000, None, 1.0, 0.006),
        (100, 100, 0.0, 0.01),
        (100, 25, 1.0, 0.06),
    ],
)
def test_sampling_the_exact_denoiser_recovers_the_data_distribution(
    num_steps, steps, eta, std_error
):
    """Gaussian data: the mean is exact; the std error is the discretisation error of the
    reverse chain (posterior variance beta~ ignores Var(x0 | x_k)), shrinking with K."""
    schedule = DiffusionSchedule(ScheduleConfig(num_steps=num_steps))
    denoiser = GaussianDenoiser(schedule, mean=0.7, std=0.3)
    levels = schedule.levels(steps)
    noise = chain_noise((20_000,), levels, torch.Generator().manual_seed(3), dtype=torch.float64)
    samples = reverse_chain(denoiser, None, noise, levels, eta)[-1]
    assert abs(float(samples.mean()) - 0.7) < 0.01
    assert abs(float(samples.std()) - 0.3) < std_error


def test_point_mass_data_is_recovered_exactly():
    schedule = DiffusionSchedule()
    denoiser = GaussianDenoiser(schedule, mean=-1.25, std=0.0)
    for steps, eta in ((None, 1.0), (10, 0.0), (10, 0.5)):
        levels = schedule.levels(steps)
        noise = chain_noise((100,), levels, torch.Generator().manual_seed(4), dtype=torch.float64)
        samples = reverse_chain(denoiser, None, noise, levels, eta)[-1]
        torch.testing.assert_close(samples, torch.full_like(samples, -1.25))


def test_levels_and_validation():
    schedule = DiffusionSchedule(ScheduleConfig(num_steps=10))
    assert schedule.levels() == [(k, k - 1) for k in range(9, -1, -1)]
    ddim = schedule.levels(4)
    assert ddim[0][0] == 9 and ddim[-1] == (0, -1)
    assert all(k > k_prev for k, k_prev in ddim)
    assert schedule.levels(1) == [(9, -1)]
    for bad in (0, 11, 2.0):
        with pytest.raises(ValueError, match="sampling_steps"):
            schedule.levels(bad)
    with pytest.raises(ValueError, match="k_prev"):
        schedule.reverse_moments(torch.zeros(1), torch.zeros(1), 3, 3, 1.0)
    with pytest.raises(ValueError, match="kind"):
        ScheduleConfig(kind="sigmoid")
    with pytest.raises(ValueError, match="num_steps"):
        ScheduleConfig(num_steps=0)
