"""Plain masked attention: fully masked rows, masked keys, finite gradients, forward AD."""

from __future__ import annotations

import torch

from policies.learned.attention import SHORT_SOFTMAX, Attention, _softmax, social_mask


def _attention(seed=0):
    torch.manual_seed(seed)
    return Attention(8, 2).double()


def test_fully_masked_rows_give_zero_output_and_finite_gradients():
    attn = _attention()
    x = torch.randn(3, 5, 8, dtype=torch.float64, requires_grad=True)
    mask = torch.ones(3, 5, 5, dtype=torch.bool)
    mask[1] = False  # a fully padded sequence
    mask[2, 4] = False  # one query that may attend to nothing
    out = attn(x, mask)
    assert torch.isfinite(out).all()
    projected_zero = attn.out(torch.zeros(8, dtype=torch.float64))
    torch.testing.assert_close(out[1], projected_zero.expand(5, 8))
    torch.testing.assert_close(out[2, 4], projected_zero)
    out.square().sum().backward()
    assert torch.isfinite(x.grad).all()


def test_masked_keys_do_not_influence_the_output():
    attn = _attention(1)
    x = torch.randn(2, 4, 8, dtype=torch.float64)
    mask = torch.ones(2, 4, 4, dtype=torch.bool)
    mask[:, :, 3] = False
    changed = x.clone()
    changed[:, 3] += 100.0
    torch.testing.assert_close(attn(x, mask)[:, :3], attn(changed, mask)[:, :3])


def test_bias_shifts_the_attention_weights():
    attn = _attention(2)
    x = torch.randn(1, 4, 8, dtype=torch.float64)
    bias = torch.zeros(1, 2, 4, 4, dtype=torch.float64)
    bias[..., 0] = 50.0  # every query looks at key 0 only
    out = attn(x, bias=bias)
    only_first = torch.zeros(1, 4, 4, dtype=torch.bool)
    only_first[..., 0] = True
    torch.testing.assert_close(out, attn(x, only_first))


def test_forward_mode_jvp_is_supported():
    attn = _attention(3)
    x, dx = torch.randn(2, 5, 8, dtype=torch.float64), torch.randn(2, 5, 8, dtype=torch.float64)
    mask = torch.rand(2, 5, 5) > 0.3
    _, tangent = torch.func.jvp(lambda y: attn(y, mask), (x,), (dx,))
    h = 1e-6
    finite = (attn(x + h * dx, mask) - attn(x - h * dx, mask)) / (2 * h)
    torch.testing.assert_close(tangent, finite, rtol=1e-6, atol=1e-8)


def test_social_mask_adds_self_attention_and_drops_padded_agents():
    pair = torch.tensor([[[False, True, False], [True, False, False], [False, False, False]]])
    agents = torch.tensor([[True, True, False]])
    expected = torch.tensor([[[True, True, False], [True, True, False], [False, False, False]]])
    assert torch.equal(social_mask(pair, agents), expected)


def test_spelled_out_softmax_of_short_rows_equals_torch_softmax():
    scores = torch.randn(3, 4, 13, 13) * 10
    scores[0, :, :, 3:] = torch.finfo(scores.dtype).min  # masked keys
    scores[1, :, 5] = torch.finfo(scores.dtype).min  # a fully masked row: uniform, as torch
    assert scores.shape[-1] < SHORT_SOFTMAX
    torch.testing.assert_close(_softmax(scores), scores.softmax(dim=-1), rtol=0, atol=1e-6)
    long = torch.randn(2, SHORT_SOFTMAX + 1)
    assert torch.equal(_softmax(long), long.softmax(dim=-1))
