"""Every options and configuration dataclass refuses a value of the wrong type with an
error naming the field (bools are not numbers, strings are not numbers, a number is not a
bool), and stores numpy scalars as Python numbers (docs/reference/configs.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from policies.baselines.diffusion.guided import DiffusionGuidanceConfig
from policies.evaluation.options import EvalOptions
from policies.learned.config import ModelConfig
from policies.learned.recovery import RecoveryConfig
from policies.learned.windows import WindowConfig
from policies.riskflow.guidance import GuidanceConfig
from policies.train import TrainOptions
from riskflow_env.render import RenderConfig
from riskflow_env.scenarios.cli import GenerateOptions
from riskflow_env.scenarios.naturalistic import SceneConfig
from riskflow_env.scenarios.traffic import TrafficConfig

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: TrafficConfig(default_speed_limit="abc"), "TrafficConfig.default_speed_limit"),
        (lambda: SceneConfig(max_agents=math.nan), "SceneConfig.max_agents must be an int"),
        (lambda: SceneConfig(window_stride=math.nan), "SceneConfig.window_stride must be an int"),
        (lambda: RecoveryConfig(seed="abc"), "RecoveryConfig.seed must be an int"),
        (lambda: EvalOptions(wosac="no"), "--wosac must be true or false"),
        (lambda: RenderConfig(show_text="no"), "RenderConfig.show_text must be true or false"),
        (lambda: WindowConfig(clip_actions=1), "WindowConfig.clip_actions must be true or false"),
        (lambda: GuidanceConfig(lambda_adv=True), "GuidanceConfig: lambda_adv must be a number"),
        (lambda: GuidanceConfig(lambda_adv="x"), "GuidanceConfig: lambda_adv must be a number"),
        (
            lambda: DiffusionGuidanceConfig(lambda_adv=True),
            "DiffusionGuidanceConfig: lambda_adv must be a number",
        ),
        (lambda: ModelConfig(time_scale=True), "ModelConfig.time_scale must be a number"),
        (lambda: TrainOptions(data="d", lr=True), "--lr must be a number"),
        (lambda: TrainOptions(data="d", resume=1), "--resume must be true or false"),
        (lambda: TrainOptions(data="d", lr=10**400), "--lr must be a finite number, got an int"),
        (lambda: RenderConfig(view_width=10**400), "RenderConfig.view_width must be a finite"),
        (lambda: TrainOptions(data="d", diffusion_schedule="x"), "--diffusion-schedule in"),
        (lambda: TrainOptions(data="d", diffusion_prediction="x"), "--diffusion-prediction in"),
    ],
)
def test_a_value_of_the_wrong_type_names_its_field(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_numpy_scalars_are_stored_as_python_numbers(tmp_path):
    guidance = GuidanceConfig(lambda_adv=np.float32(0.5), steps=np.int64(3))
    assert type(guidance.lambda_adv) is float and guidance.lambda_adv == 0.5
    assert type(guidance.steps) is int
    assert GenerateOptions(out=tmp_path / "bank", stop_share=np.float32(0.1)).stop_share == 0.1
    options = TrainOptions(data="d", lr=np.float32(1e-4), steps=np.int64(5))
    assert type(options.lr) is float and options.lr == 1e-4 and type(options.steps) is int
    assert type(EvalOptions(duration=np.float64(2.0)).duration) is float
