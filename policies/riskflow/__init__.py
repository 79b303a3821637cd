"""The RiskFlow adversary: what is RiskFlow's on top of the shared layer (:mod:`policies.learned`).

* :mod:`~policies.riskflow.meanflow`: the MeanFlow objective (and the flow-matching
  reference) over the shared network;
* :mod:`~policies.riskflow.time_sampler`: the ``(t, r)`` sampler of training;
* :mod:`~policies.riskflow.guidance`: output-space gradient guidance of the top-K plans;
* :mod:`~policies.riskflow.base_generator`: which generator the adversary plans with;
* :mod:`~policies.riskflow.policy`: :class:`RiskFlowAdversary`, the scene policy;
* :mod:`~policies.train`: ``riskflow-train``.
"""

from policies.riskflow.guidance import GuidanceConfig, guide
from policies.riskflow.meanflow import flow_matching_loss, meanflow_loss
from policies.riskflow.policy import RiskFlowAdversary
from policies.riskflow.time_sampler import TimeSampler

__all__ = [
    "GuidanceConfig",
    "RiskFlowAdversary",
    "TimeSampler",
    "flow_matching_loss",
    "guide",
    "meanflow_loss",
]
