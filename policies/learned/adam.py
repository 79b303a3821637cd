"""Adam on one tensor of variables, as a function of the gradients (no autograd state).

The inference-time optimisations of plans (output-space guidance,
:mod:`policies.riskflow.guidance`; avoidance steps,
:mod:`policies.learned.plan_avoidance`) compute their gradients in closed form and step
tensors that are not ``torch.nn.Parameter``s, inside ``torch.inference_mode``, where
``torch.optim.Adam`` cannot run. The update is Adam's (Kingma & Ba 2015, "Adam: A Method
for Stochastic Optimization", ICLR, Algorithm 1, with ``torch.optim.Adam``'s defaults):

    m <- b1 m + (1 - b1) g,   v <- b2 v + (1 - b2) g^2,
    step = lr / (1 - b1^t) * m / (sqrt(v / (1 - b2^t)) + 1e-8).

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
    """

    def __init__(self, like: Tensor, learning_rate: float) -> None:
        self.first = like.new_zeros(like.shape)
        self.second = like.new_zeros(like.shape)
        self.learning_rate, self.count = learning_rate, 0

    def select(self, rows: Tensor) -> None:
        """Keep the moments of the variables' rows ``rows`` (indices or a bool mask along
        dimension 0) only, for a loop that drops the rows it has finished with."""
        self.first = self.first[rows]
        self.second = self.second[rows]

    def step(self, gradient: Tensor) -> Tensor:
        """The update of this step (``lr * m_hat / (sqrt(v_hat) + eps)``) for ``gradient``."""
        beta1, beta2 = BETAS
        self.count += 1
        self.first.mul_(beta1).add_(gradient, alpha=1 - beta1)
        self.second.mul_(beta2).addcmul_(gradient, gradient, value=1 - beta2)
        scale = self.learning_rate / (1 - beta1**self.count)
        return scale * self.first / ((self.second / (1 - beta2**self.count)).sqrt() + EPSILON)


__all__ = ["Adam"]
