"""The RiskFlow adversary: window data, encoder, MeanFlow generator, guidance, policy."""

from policies.riskflow.config import ModelConfig
from policies.riskflow.encoder import SceneContext, SceneEncoder
from policies.riskflow.generator import CheckpointError, MeanFlowHead, RiskFlowGenerator
from policies.riskflow.guidance import GuidanceConfig, guide
from policies.riskflow.meanflow import flow_matching_loss, meanflow_loss
from policies.riskflow.policy import RiskFlowAdversary
from policies.riskflow.ranking import Ranking, causal_ranking
from policies.riskflow.sampler import base_velocity, sample
from policies.riskflow.time_sampler import TimeSampler

__all__ = [
    "CheckpointError",
    "GuidanceConfig",
    "MeanFlowHead",
    "ModelConfig",
    "Ranking",
    "RiskFlowAdversary",
    "RiskFlowGenerator",
    "SceneContext",
    "SceneEncoder",
    "TimeSampler",
    "base_velocity",
    "causal_ranking",
    "flow_matching_loss",
    "guide",
    "meanflow_loss",
    "sample",
]
