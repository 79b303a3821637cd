"""Checkpoint files: round trip, metadata, mismatches, atomic writing, the shipped default."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest
import torch

from policies.learned import checkpoint as checkpoint_module
from policies.learned.checkpoint import (
    build_checkpoint,
    code_version,
    load_checkpoint,
    load_generator,
    save_checkpoint,
)
from policies.learned.generator import CheckpointError, RiskFlowGenerator
from policies.learned.sampler import sample
from policies.learned.synthetic import synthetic_batch
from riskflow_env.scenarios import save_scenario, shipped_bank


def _write(path, model, stats, **overrides):
    checkpoint = build_checkpoint(
        model, stats, step=12, train_config={"lr": 1e-4}, metrics={"val_ade": 1.5}
    )
    checkpoint.update(overrides)
    return save_checkpoint(checkpoint, path)


def test_round_trip_gives_identical_samples(tmp_path, make_model, normalizer, tiny_config):
    model = make_model(tiny_config, seed=3).eval()
    path = _write(tmp_path / "generator.pt", model, normalizer)
    loaded, loaded_normalizer, metadata = load_generator(path)
    assert loaded_normalizer == normalizer
    assert metadata["step"] == 12 and metadata["metrics"] == {"val_ade": 1.5}
    assert metadata["train_config"] == {"lr": 1e-4}
    assert metadata["version"] == code_version()
    assert not loaded.training and not any(p.requires_grad for p in loaded.parameters())
    batch = synthetic_batch(2, 5, seed=1)
    eps = torch.randn(2, 5, 52, 2, generator=torch.Generator().manual_seed(0))
    expected = sample(model, batch, eps, normalizer)
    for got, want in zip(sample(loaded, batch, eps, loaded_normalizer), expected, strict=True):
        torch.testing.assert_close(got, want, rtol=0, atol=0)
    # the file is also a plain generator checkpoint
    rebuilt = RiskFlowGenerator.from_checkpoint(load_checkpoint(path))
    assert rebuilt.config == tiny_config


def test_a_stored_map_ahead_loads_when_zero_and_is_refused_otherwise(
    tmp_path, make_model, normalizer, tiny_config
):
    """Files of the versions that had ``ModelConfig.map_ahead`` store it: 0 (the centred
    crop) loads as before, anything else is refused with the field named."""
    model = make_model(tiny_config).eval()
    config = model.checkpoint()["config"]
    centred = _write(tmp_path / "a.pt", model, normalizer, config=config | {"map_ahead": 0.0})
    assert load_generator(centred)[0].config == tiny_config
    ahead = _write(tmp_path / "b.pt", model, normalizer, config=config | {"map_ahead": 12.0})
    with pytest.raises(CheckpointError, match=r"map_ahead = 12\.0.*centred on its agent"):
        load_generator(ahead)


def test_mismatches_raise_clear_errors(tmp_path, make_model, normalizer, tiny_config):
    model = make_model(tiny_config)
    path = _write(tmp_path / "a.pt", model, normalizer)
    other = dataclasses.replace(tiny_config, head_layers=2)
    with pytest.raises(CheckpointError, match="head_layers"):
        load_generator(path, config=other)
    state = dict(load_checkpoint(path)["state_dict"])
    state["head.out.weight"] = torch.zeros(3, 3)
    bad_shape = _write(tmp_path / "b.pt", model, normalizer, state_dict=state)
    with pytest.raises(CheckpointError, match=r"head\.out\.weight"):
        load_generator(bad_shape)
    no_stats = _write(tmp_path / "c.pt", model, normalizer, normalizer=None)
    with pytest.raises(CheckpointError, match="normalizer"):
        load_generator(no_stats)
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="cannot read"):
        load_generator(tmp_path / "junk.pt")
    with pytest.raises(FileNotFoundError, match="no generator checkpoint"):
        load_generator(tmp_path / "missing.pt")


def test_a_file_the_safe_loader_refuses_is_named_in_one_short_line(tmp_path):
    foreign = tmp_path / "foreign.pt"
    foreign.write_bytes(pickle.dumps({"weights": np.zeros(3)}, protocol=4))
    text = tmp_path / "notes.pt"
    text.write_text("# my notes\n")
    with_numpy = tmp_path / "numpy.pt"
    torch.save({"weights": np.zeros(3)}, with_numpy)
    module = tmp_path / "module.pt"
    torch.save(torch.nn.Linear(2, 2), module)
    with pytest.raises(CheckpointError, match="notes.pt: not a file written by torch.save$"):
        load_checkpoint(text)  # neither a zip nor a pickle: not handed to the loader
    for path in (foreign, with_numpy, module):
        with pytest.raises(CheckpointError) as raised:
            load_checkpoint(path)
        message = str(raised.value)
        assert "the safe loader refuses it" in message and path.name in message
        assert "\n" not in message and len(message) < 300
        for advice in ("weights_only", "add_safe_globals", "trust"):
            assert advice not in message
    with pytest.raises(CheckpointError, match=r"it holds torch\.nn\.modules\.linear\.Linear"):
        load_checkpoint(module)


def test_empty_text_and_folder_checkpoints_say_what_they_are(tmp_path):
    (tmp_path / "empty.pt").write_bytes(b"")
    (tmp_path / "hello.pt").write_text("hello\n")
    (tmp_path / "folder.pt").mkdir()
    with pytest.raises(CheckpointError, match="empty.pt: the file is empty or truncated"):
        load_checkpoint(tmp_path / "empty.pt")
    with pytest.raises(CheckpointError, match="hello.pt: not a file written by torch.save$"):
        load_checkpoint(tmp_path / "hello.pt")
    # other text made torch's legacy reader fail with "list index out of range"
    (tmp_path / "passwd.pt").write_text("root:x:0:0:root:/root:/bin/bash\n")
    with pytest.raises(CheckpointError, match="passwd.pt: not a file written by torch.save$"):
        load_checkpoint(tmp_path / "passwd.pt")
    scene = save_scenario(shipped_bank("eval")[0], tmp_path / "scene.npz")  # a zip, not torch's
    with pytest.raises(CheckpointError, match="scene.npz: not a file written by torch.save$"):
        load_checkpoint(scene)
    with pytest.raises(IsADirectoryError, match="folder.pt is a folder, not a generator"):
        load_checkpoint(tmp_path / "folder.pt")


def test_save_is_atomic(tmp_path, make_model, normalizer, tiny_config, monkeypatch):
    model = make_model(tiny_config)
    path = _write(tmp_path / "g.pt", model, normalizer)
    before = path.read_bytes()

    def broken_save(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        _write(path, model, normalizer)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["g.pt"], "no temporary file is left"


def test_default_checkpoint(monkeypatch):
    shipped = checkpoint_module.resources.files("policies") / "checkpoints" / "riskflow_default.pt"
    if shipped.is_file():
        model, normalizer, metadata = load_generator()
        assert isinstance(model, RiskFlowGenerator) and metadata["step"] > 0
        assert shipped.stat().st_size <= 20e6
    monkeypatch.setattr(checkpoint_module, "DEFAULT_NAME", "does-not-exist.pt")
    with pytest.raises(FileNotFoundError, match="riskflow-train"):
        load_generator()


def test_loading_the_shipped_generator_does_not_import_dynamo():
    """The shipped architecture is built once, off the meta device, whose Python kernels
    import torch._dynamo (seconds in every fresh process)."""
    import subprocess
    import sys

    code = (
        "import sys; from policies.learned.checkpoint import load_generator; "
        "load_generator(); print('torch._dynamo' in sys.modules)"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=300
    )
    assert result.stdout.strip().splitlines()[-1] == "False"


def test_a_checkpoint_is_read_once_and_again_when_it_changes(tmp_path, make_model, normalizer):
    """read_checkpoint keeps a file it read while the file is unchanged; a caller's
    changes to what it got do not reach the next caller."""
    path = _write(tmp_path / "generator.pt", make_model(seed=1), normalizer)
    first = checkpoint_module.read_checkpoint(path, "unused", "generator", "")
    first["train_config"]["lr"] = 99.0
    first["state_dict"] = {}
    second = checkpoint_module.read_checkpoint(path, "unused", "generator", "")
    assert second["train_config"] == {"lr": 1e-4} and second["state_dict"]
    _write(path, make_model(seed=2), normalizer, step=13)  # a new file at the same path
    assert checkpoint_module.read_checkpoint(path, "unused", "generator", "")["step"] == 13
