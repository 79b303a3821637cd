"""Hostile generator checkpoints (issue 53): refused from the tensors' metadata before
anything materialises them, or for non-finite weights, with a ``CheckpointError`` naming
the file and the tensor, within a CPU-time bound and 500 MB.

Every file is built here from the shipped checkpoint and loaded by ``load_generator`` in
a child process whose address space is capped at 1.5 GB (:mod:`tests.capped`).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from policies.learned.checkpoint import save_checkpoint
from tests.capped import Outcome, assert_bounded, run_capped

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md

SHIPPED = Path("policies/checkpoints/riskflow_default.pt")
SETUP = "from policies.learned.checkpoint import load_generator"
WEIGHT = "encoder.token_pos"  # a float32 tensor of the shipped state dict


def _refused(outcome: Outcome, path: Path, *fragments: str) -> None:
    """A CheckpointError naming ``path`` and every fragment, within a CPU-time bound and 500 MB."""
    assert outcome.error == "CheckpointError", outcome
    assert path.name in outcome.message and outcome.chars < 1000, outcome
    for fragment in fragments:
        assert fragment in outcome.message, (fragment, outcome.message)
    assert_bounded(outcome)


def _load(path: Path) -> Outcome:
    return run_capped(SETUP, f"load_generator({str(path)!r})")


def _shipped() -> dict:
    return torch.load(SHIPPED, weights_only=True)


def _saved(tmp_path: Path, checkpoint: dict, name: str = "hostile.pt") -> Path:
    """``checkpoint`` written as it is (its stored digest kept: computing one would
    materialise the hostile tensor here)."""
    path = tmp_path / name
    torch.save(checkpoint, path)
    assert path.stat().st_size < 10 * 2**20
    return path


@pytest.mark.parametrize(
    ("tensor", "fragment"),
    [
        (torch.zeros(1).expand(2**28), "strides (0,)"),  # 1 GiB from 4 bytes
        (torch.zeros(1).expand(2**36), "strides (0,)"),  # 256 GiB
        (torch.zeros(2**16).as_strided((2**15, 2**15), (1, 1)), "strides (1, 1)"),  # overlap
    ],
)
def test_expanded_tensor_refused_before_the_digest(tmp_path, tensor, fragment):
    checkpoint = _shipped()
    checkpoint["state_dict"][WEIGHT] = tensor
    path = _saved(tmp_path, checkpoint)
    _refused(_load(path), path, f"state_dict['{WEIGHT}']", "expanded", fragment)


def test_expanded_tensor_in_the_training_state_refused(tmp_path):
    checkpoint = _shipped() | {"training": {"optimizer": {"m": torch.zeros(1).expand(2**30)}}}
    path = _saved(tmp_path, checkpoint)
    _refused(_load(path), path, "training['optimizer']['m']", "expanded")


def test_many_views_of_one_storage_refused(tmp_path):
    checkpoint = _shipped()
    storage = torch.zeros(2**20)  # 4 MiB, stored once
    checkpoint["state_dict"] |= {f"view{i}": storage[:] for i in range(300)}  # 1.2 GiB
    path = _saved(tmp_path, checkpoint)
    _refused(_load(path), path, "MAX_TENSOR_BYTES")


def test_sparse_tensor_refused(tmp_path):
    checkpoint = _shipped()
    checkpoint["state_dict"][WEIGHT] = torch.zeros(4, 4).to_sparse()
    path = _saved(tmp_path, checkpoint)
    _refused(_load(path), path, f"state_dict['{WEIGHT}']", "layout")


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_weights_refused_naming_the_tensor(tmp_path, value):
    checkpoint = _shipped()
    checkpoint["state_dict"][WEIGHT][0, 0] = value
    path = save_checkpoint(checkpoint, tmp_path / "diverged.pt")  # a valid digest
    _refused(_load(path), path, f"state_dict['{WEIGHT}']", "NaN or inf")


def test_oversized_normalizer_refused(tmp_path):
    checkpoint = _shipped()
    checkpoint["normalizer"] = dict(checkpoint["normalizer"], mean=[0.0] * 100_000)
    path = _saved(tmp_path, checkpoint)
    _refused(_load(path), path, "normalizer")
