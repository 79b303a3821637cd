"""Checkpoints carry their kind and a weights checksum, verified on load (issue 19 item 4)."""

from __future__ import annotations

import resource
import warnings

import pytest
import torch

from policies.learned.checkpoint import (
    load_checkpoint,
    load_generator,
    save_checkpoint,
    weights_digest,
)
from policies.learned.generator import CheckpointError

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md

SHIPPED = "policies/checkpoints/riskflow_default.pt"
DIFFUSION = "policies/checkpoints/diffusion_default.pt"


def _shipped():
    return load_checkpoint(SHIPPED)


@pytest.mark.parametrize(("path", "kind"), [(SHIPPED, "meanflow"), (DIFFUSION, "diffusion")])
def test_shipped_checkpoints_carry_kind_and_a_verified_digest(path, kind):
    raw = torch.load(path, weights_only=True)
    assert raw["kind"] == kind and raw["weights_sha256"] == weights_digest(raw["state_dict"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # verified: no "cannot be verified" warning
        load_checkpoint(path)


def test_checkpoint_without_digest_loads_with_a_warning(tmp_path):
    old = {k: v for k, v in _shipped().items() if k not in ("kind", "weights_sha256")}
    torch.save(old, tmp_path / "old.pt")  # as written before digests existed
    with pytest.warns(UserWarning, match="no weights_sha256"):
        model, _, _ = load_generator(tmp_path / "old.pt")
    assert model.num_parameters() > 0


def test_diffusion_checkpoint_refused_by_load_generator():
    with pytest.raises(CheckpointError, match="diffusion"):
        load_generator(DIFFUSION)


def test_save_writes_kind_and_digest_and_round_trips(tmp_path):
    path = save_checkpoint(_shipped(), tmp_path / "g.pt")
    raw = torch.load(path, weights_only=True)
    assert raw["kind"] == "meanflow" and len(raw["weights_sha256"]) == 64
    model, _, _ = load_generator(path)  # no warning needed: verified
    assert model.num_parameters() > 0


def test_int8_weights_refused(tmp_path):
    checkpoint = _shipped()
    name = next(k for k, v in checkpoint["state_dict"].items() if v.is_floating_point())
    checkpoint["state_dict"][name] = checkpoint["state_dict"][name].to(torch.int8)
    path = save_checkpoint(checkpoint, tmp_path / "int8.pt")
    with pytest.raises(CheckpointError, match="dtype"):
        load_generator(path)


def test_one_flipped_byte_refused(tmp_path):
    checkpoint = _shipped()
    path = save_checkpoint(checkpoint, tmp_path / "g.pt")
    name, tensor = max(checkpoint["state_dict"].items(), key=lambda item: item[1].numel())
    needle = tensor.contiguous().numpy().tobytes()[:64]
    data = bytearray(path.read_bytes())
    offset = data.find(needle)
    assert offset > 0
    data[offset + 10] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="weights_sha256"):
        load_generator(path)


def test_huge_encoder_dim_refused_before_allocation(tmp_path):
    checkpoint = _shipped()
    checkpoint["config"] = dict(checkpoint["config"], encoder_dim=400_000)
    path = save_checkpoint(checkpoint, tmp_path / "huge.pt")
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    with pytest.raises(CheckpointError, match="shape"):
        load_generator(path)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - before < 1000
