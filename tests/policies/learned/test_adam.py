"""The gradient-function Adam of the inference-time optimisations (policies.learned.adam)."""

import pytest
import torch

from policies.learned.adam import EPSILON, Adam


def _gradients(steps: int, shape: tuple[int, ...], seed: int = 0) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    return [torch.randn(shape, generator=generator, dtype=torch.float64) for _ in range(steps)]


def test_per_coordinate_steps_are_torch_adams():
    gradients = _gradients(5, (3, 7, 2))
    variable = torch.zeros(3, 7, 2, dtype=torch.float64, requires_grad=True)
    reference = torch.optim.Adam([variable], lr=0.1)
    adam, ours = Adam(variable.detach(), 0.1), torch.zeros_like(variable.detach())
    for gradient in gradients:
        variable.grad = gradient.clone()
        reference.step()
        ours -= adam.step(gradient)
    torch.testing.assert_close(ours, variable.detach(), rtol=1e-10, atol=1e-12)


def test_a_shared_block_steps_along_its_gradient():
    """One second moment per (7, 2) block: the first step is lr * g / rms(g) per block, so
    its shape is the gradient's, whatever each block's scale."""
    gradient = (
        _gradients(1, (3, 7, 2))[0]
        * torch.tensor([1e-3, 1.0, 1e3], dtype=torch.float64)[:, None, None]
    )
    step = Adam(gradient, 0.1, shared=(1, 2)).step(gradient)
    rms = gradient.pow(2).mean(dim=(1, 2), keepdim=True).sqrt()
    torch.testing.assert_close(step, 0.1 * gradient / (rms + EPSILON), rtol=1e-9, atol=0.0)
    torch.testing.assert_close(
        step.pow(2).mean(dim=(1, 2)).sqrt(), torch.full((3,), 0.1).double(), rtol=1e-4, atol=0.0
    )
    assert Adam(gradient, 0.1, shared=(-1, -2)).second.shape == (3, 1, 1)


@pytest.mark.parametrize("shared", [(), (1, 2)])
def test_rows_do_not_interact(shared):
    """A block's steps depend on its own gradients only (batched guidance is row-wise)."""
    gradients = _gradients(4, (4, 6, 2))
    together, alone = Adam(gradients[0], 0.05, shared), Adam(gradients[0][:1], 0.05, shared)
    for gradient in gradients:
        torch.testing.assert_close(together.step(gradient)[:1], alone.step(gradient[:1]))
