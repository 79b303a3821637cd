"""Packed real agents: the network's outputs equal those of running every padded slot."""

from __future__ import annotations

import pytest
import torch

import riskflow_env
from policies.learned.attention import Attention, social_mask
from policies.learned.checkpoint import load_generator
from policies.learned.packing import MAX_SCENE_GROUPS, MIN_GROUP_SCENES, AgentPacking
from policies.learned.sampler import base_velocity
from policies.learned.synthetic import synthetic_batch
from policies.learned.window_types import collate_windows
from policies.learned.windows import window_from_view
from policies.riskflow.meanflow import meanflow_loss
from policies.riskflow.time_sampler import TimeSampler
from riskflow_env.scenarios import shipped_bank

# Shipped evaluation scenes of 8 to 48 vehicles (windows of 8 to 32 agents): 16, so that
# social attention splits them into scene groups (packing.MIN_GROUP_SCENES).
SCENES = (14, 5, 0, 3, *range(6, 14), 15, 16, 19, 20)


@pytest.fixture
def padded_layout(monkeypatch):
    """Every slot treated as real: the per-agent layers run on the padded layout too."""

    def every_slot(cls, agent_mask: torch.Tensor) -> AgentPacking:
        return cls(None, *agent_mask.shape)

    def use() -> None:
        monkeypatch.setattr(AgentPacking, "from_mask", classmethod(every_slot))

    return use


def test_pack_and_unpack_round_trip():
    mask = torch.tensor([[True, False, True], [False, False, True]])
    packing = AgentPacking.from_mask(mask)
    x = torch.arange(6.0).reshape(2, 3)
    assert packing.pack(x).tolist() == [0.0, 2.0, 5.0]
    assert packing.unpack(packing.pack(x)).tolist() == [[0.0, 0.0, 2.0], [0.0, 0.0, 5.0]]
    full = AgentPacking.from_mask(torch.ones(2, 3, dtype=torch.bool))
    assert full.index is None and torch.equal(full.unpack(full.pack(x)), x)


def test_scene_groups_hold_every_real_agent_once():
    widths = torch.randint(1, 33, (40,), generator=torch.Generator().manual_seed(0))
    mask = torch.arange(32) < widths[:, None]
    mask[3, 0] = False  # a hole: the real agents need not come first
    packing = AgentPacking.from_mask(mask)
    assert len(packing.groups) == MAX_SCENE_GROUPS
    rows = torch.cat([group.rows for group in packing.groups])
    assert torch.equal(rows.sort().values, torch.arange(int(mask.sum())))
    assert torch.equal(rows[packing.order], torch.arange(len(rows)))
    for group in packing.groups:
        assert len(group.scenes) >= MIN_GROUP_SCENES
        assert not mask[group.scenes, group.width :].any()
    assert not AgentPacking.from_mask(mask[:8]).groups  # too few scenes to split


def test_grouped_social_attention_equals_one_padded_batch():
    torch.manual_seed(0)
    attention = Attention(8, 2).double()
    widths = torch.randint(1, 13, (20,))
    agent_mask = torch.arange(12) < widths[:, None]
    pair_mask = torch.rand(20, 12, 12) < 0.7
    mask = social_mask(pair_mask, agent_mask)[:, None]  # (B, 1, A, A): every token
    bias = torch.randn(20, 1, 2, 12, 12, dtype=torch.float64)
    grouped = AgentPacking.from_mask(agent_mask)
    assert grouped.groups
    x = torch.randn(int(agent_mask.sum()), 5, 8, dtype=torch.float64)
    one_batch = AgentPacking.from_mask(agent_mask, grouped=False)
    torch.testing.assert_close(
        attention(x, mask, bias, grouped), attention(x, mask, bias, one_batch)
    )


def test_packed_network_equals_padded_on_very_different_agent_counts(padded_layout):
    """The shipped model on 16 shipped scenes of 8 to 32 window agents (most slots of the
    small scenes padded; social attention in scene groups): context and one-step velocity
    of the real agents as with every slot computed, within 1e-5; padded slots are zero."""
    model, _, _ = load_generator()
    windows = []
    for index in SCENES:
        scenario = shipped_bank("eval")[index]
        env = riskflow_env.parallel_env(scenarios=scenario)
        env.reset(seed=0, options={"scenario": scenario})
        windows.append(window_from_view(env.view()))
    batch = collate_windows(windows)
    counts = batch.agent_mask.sum(dim=1).tolist()
    assert min(counts) <= 8 and max(counts) == batch.num_agents >= 30, counts
    assert len(AgentPacking.from_mask(batch.agent_mask.bool()).groups) == 2
    mask = batch.agent_mask.bool()
    eps = torch.randn(*mask.shape, 52, 2, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        scene = model.encode(batch)
        u = base_velocity(model, eps, scene)
        padded_layout()
        scene_padded = model.encode(batch)
        u_padded = base_velocity(model, eps, scene_padded)
    assert not scene.context[~mask].any() and not u[~mask].any()
    torch.testing.assert_close(scene.context[mask], scene_padded.context[mask], rtol=0, atol=1e-5)
    torch.testing.assert_close(u[mask], u_padded[mask], rtol=0, atol=1e-5)


def test_packed_training_loss_and_gradients_equal_padded(make_model, normalizer, padded_layout):
    """The MeanFlow objective (its JVP goes through the packing and the scene groups) on a
    padded batch."""
    batch = synthetic_batch(16, 8, seed=3)
    assert AgentPacking.from_mask(batch.agent_mask.bool()).groups
    model = make_model()

    def loss_and_grads() -> tuple[torch.Tensor, list[torch.Tensor]]:
        model.zero_grad()
        eps = torch.randn(batch.actions.shape, generator=torch.Generator().manual_seed(1))
        times = TimeSampler(equal_fraction=0.5)
        t, r = times(batch.batch_size, generator=torch.Generator().manual_seed(2))
        loss = meanflow_loss(model, batch, normalizer, eps, t, r)[0]
        loss.backward()
        return loss.detach(), [p.grad.clone() for p in model.parameters() if p.grad is not None]

    loss, grads = loss_and_grads()
    padded_layout()
    loss_padded, grads_padded = loss_and_grads()
    torch.testing.assert_close(loss, loss_padded, rtol=1e-5, atol=1e-6)
    assert len(grads) == len(grads_padded)
    for grad, grad_padded in zip(grads, grads_padded, strict=True):
        torch.testing.assert_close(grad, grad_padded, rtol=1e-4, atol=1e-5)
