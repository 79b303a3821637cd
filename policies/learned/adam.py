"""Adam on one tensor of variables, as a function of the gradients (no autograd state).

The inference-time optimisations of plans (output-space guidance,
:mod:`policies.riskflow.guidance`; avoidance steps,
:mod:`policies.learned.plan_avoidance`) compute their gradients in closed form and step
tensors that are not ``torch.nn.Parameter``s, inside ``torch.inference_mode``, where
``torch.optim.Adam`` cannot run. The update is Adam's (Kingma & Ba 2015, "Adam: A Method
for Stochastic Optimization", ICLR, Algorithm 1, with ``torch.optim.Adam``'s defaults):

    m <- b1 m + (1 - b1) g,   v <- b2 v + (1 - b2) g^2,
    step = lr / (1 - b1^t) * m / (sqrt(v / (1 - b2^t)) + 1e-8).

With ``shared`` dimensions the second moment is one per block instead of one per
coordinate: ``g^2`` is averaged over those dimensions (Adam-mini: Zhang et al. 2024,
"Adam-mini: Use Fewer Learning Rates To Gain More", one second moment per parameter
block). A block's step then keeps the shape of its gradient (the first step is
``lr * g / rms(g)``) where per-coordinate Adam moves every coordinate by about ``lr``.
Output-space guidance (:mod:`policies.riskflow.guidance`) and STRIVE-style's latent
optimisation (:mod:`policies.baselines.strive`) use it with one block per guided plan or
latent row (``optimizer="adam-plan"``, an option).
"""

from __future__ import annotations

from torch import Tensor

BETAS = (0.9, 0.999)
EPSILON = 1e-8


class Adam:
    """The moments of one tensor of variables; :meth:`step` returns the move to subtract.

    Args:
        like: a tensor of the variables' shape, dtype and device.
        learning_rate: ``lr`` [units of the variables per step].
        shared: dimensions of ``like`` over which one second moment is shared (module
            docstring); () (default): one per coordinate, Adam's.
    """

    def __init__(self, like: Tensor, learning_rate: float, shared: tuple[int, ...] = ()) -> None:
        self.first = like.new_zeros(like.shape)
        dims = {dim % like.dim() for dim in shared}
        self.second = like.new_zeros([1 if d in dims else n for d, n in enumerate(like.shape)])
        self.learning_rate, self.count, self.shared = learning_rate, 0, tuple(shared)
        self._row_shared = 0 in dims

    def select(self, rows: Tensor) -> None:
        """Keep the moments of the variables' rows ``rows`` (indices or a bool mask along
        dimension 0) only, for a loop that drops the rows it has finished with."""
        self.first = self.first[rows]
        if not self._row_shared:
            self.second = self.second[rows]

    def step(self, gradient: Tensor) -> Tensor:
        """The update of this step (``lr * m_hat / (sqrt(v_hat) + eps)``) for ``gradient``."""
        beta1, beta2 = BETAS
        self.count += 1
        self.first.mul_(beta1).add_(gradient, alpha=1 - beta1)
        if self.shared:
            square = (gradient * gradient).mean(dim=self.shared, keepdim=True)
            self.second.mul_(beta2).add_(square, alpha=1 - beta2)
        else:
            self.second.mul_(beta2).addcmul_(gradient, gradient, value=1 - beta2)
        scale = self.learning_rate / (1 - beta1**self.count)
        return scale * self.first / ((self.second / (1 - beta2**self.count)).sqrt() + EPSILON)


__all__ = ["Adam"]
