"""Generator wrapper: shapes, adaLN-Zero init, checkpoints, ModelConfig, CUDA."""

from __future__ import annotations

import dataclasses
import io

import pytest
import torch

from policies.learned.config import ModelConfig
from policies.learned.generator import CheckpointError, RiskFlowGenerator
from policies.learned.sampler import sample
from policies.learned.synthetic import synthetic_batch
from policies.riskflow.meanflow import meanflow_loss
from policies.riskflow.time_sampler import TimeSampler


def _inputs(batch_size=2, agents=5, seed=0):
    batch = synthetic_batch(batch_size, agents, seed=seed)
    z = torch.randn(batch_size, agents, 52, 2, generator=torch.Generator().manual_seed(seed))
    return batch, z, torch.full((batch_size,), 0.25), torch.full((batch_size,), 0.75)


def test_average_velocity_shape_and_zero_at_initialisation(tiny_config):
    batch, z, t, r = _inputs()
    model = RiskFlowGenerator(tiny_config)
    u = model(batch, z, t, r)
    assert u.shape == z.shape
    assert not u.any(), "adaLN-Zero: the head starts at u = 0"


def test_per_agent_times_and_padded_agents(make_model):
    batch, z, t, r = _inputs()
    model = make_model()
    u_scene = model(batch, z, t, r)
    u_agents = model(batch, z, t[:, None].expand(2, 5), r[:, None].expand(2, 5))
    torch.testing.assert_close(u_agents, u_scene)
    assert u_scene.abs().sum() > 0
    assert not u_scene[~batch.agent_mask].any()


def test_z_of_the_wrong_shape_is_rejected(make_model):
    batch, z, t, r = _inputs()
    with pytest.raises(ValueError, match=r"z must have shape \(B, A, T, 2\)"):
        make_model()(batch, z[:, :, :50], t, r)


def test_checkpoint_round_trip_through_torch_save(make_model, tiny_config):
    model = make_model(seed=4)
    buffer = io.BytesIO()
    torch.save(model.checkpoint(), buffer)
    buffer.seek(0)
    loaded = RiskFlowGenerator.from_checkpoint(torch.load(buffer), config=tiny_config)
    assert loaded.config == tiny_config
    batch, z, t, r = _inputs()
    assert torch.equal(loaded(batch, z, t, r), model(batch, z, t, r))


def test_mismatched_checkpoints_raise_clear_errors(make_model, tiny_config):
    checkpoint = make_model().checkpoint()
    other = dataclasses.replace(tiny_config, head_dim=48)
    with pytest.raises(CheckpointError, match=r"head_dim.*\(48, 32\)"):
        RiskFlowGenerator.from_checkpoint(checkpoint, config=other)
    with pytest.raises(CheckpointError, match="format"):
        RiskFlowGenerator.from_checkpoint({"state_dict": checkpoint["state_dict"]})
    bad_config = dict(checkpoint, config={**checkpoint["config"], "layers": 3})
    with pytest.raises(CheckpointError, match="unknown field.*layers"):
        RiskFlowGenerator.from_checkpoint(bad_config)
    state = dict(checkpoint["state_dict"])
    state.pop("head.out.bias")
    state["head.in_proj.weight"] = torch.zeros(3, 3)
    with pytest.raises(CheckpointError, match=r"missing \['head.out.bias'\].*head.in_proj.weight"):
        RiskFlowGenerator.from_checkpoint(dict(checkpoint, state_dict=state))
    with pytest.raises(CheckpointError, match="shape mismatches"):
        RiskFlowGenerator(other).load_checkpoint_state(checkpoint["state_dict"])


def test_model_config_validates_and_round_trips():
    config = ModelConfig()
    assert ModelConfig.from_dict(config.to_dict()) == config
    assert config.history_tokens == 8 and config.plan_tokens == 13
    with pytest.raises(ValueError, match="plan_patch"):
        ModelConfig(plan_patch=5)
    with pytest.raises(ValueError, match="num_heads"):
        ModelConfig(head_dim=50)
    with pytest.raises(ValueError, match="pair_scale"):
        ModelConfig(pair_scale=(1.0,) * 7)
    with pytest.raises(ValueError, match="encoder_layers"):
        ModelConfig(encoder_layers=0)


def test_default_model_is_cpu_sized():
    assert RiskFlowGenerator().num_parameters() < 2_000_000


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_model_trains_and_samples_on_cuda(make_model, normalizer):
    device = torch.device("cuda")
    model = make_model().to(device)
    batch = synthetic_batch(2, 5, seed=0, device=device)
    gen = torch.Generator(device=device).manual_seed(0)
    t, r = TimeSampler()(2, generator=gen, device=device)
    eps = torch.randn(batch.actions.shape, generator=gen, device=device)
    loss, _ = meanflow_loss(model, batch, normalizer, eps, t, r)
    loss.backward()
    assert torch.isfinite(loss) and all(p.grad.is_cuda for p in model.parameters())
    actions, trajectories = sample(model, batch, eps, normalizer)
    assert actions.is_cuda and torch.isfinite(trajectories).all()
