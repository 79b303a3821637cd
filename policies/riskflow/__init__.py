"""The RiskFlow adversary: window data, encoder, MeanFlow generator, guidance, policy."""

from policies.riskflow.config import ModelConfig
from policies.riskflow.encoder import SceneContext, SceneEncoder
from policies.riskflow.generator import CheckpointError, MeanFlowHead, RiskFlowGenerator
from policies.riskflow.meanflow import flow_matching_loss, meanflow_loss
from policies.riskflow.sampler import base_velocity, sample
from policies.riskflow.time_sampler import TimeSampler

__all__ = [
    "CheckpointError",
    "MeanFlowHead",
    "ModelConfig",
    "RiskFlowGenerator",
    "SceneContext",
    "SceneEncoder",
    "TimeSampler",
    "base_velocity",
    "flow_matching_loss",
    "meanflow_loss",
    "sample",
]
