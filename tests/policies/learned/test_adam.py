"""The gradient-function Adam of the inference-time optimisations (policies.learned.adam)."""

import torch

from policies.learned.adam import Adam


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


def test_rows_do_not_interact():
    """A row's steps depend on its own gradients only (batched guidance is row-wise)."""
    gradients = _gradients(4, (4, 6, 2))
    together, alone = Adam(gradients[0], 0.05), Adam(gradients[0][:1], 0.05)
    for gradient in gradients:
        torch.testing.assert_close(together.step(gradient)[:1], alone.step(gradient[:1]))
