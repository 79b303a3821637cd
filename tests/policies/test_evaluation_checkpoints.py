"""riskflow-eval and checkpoint files: the rows of a checkpoint retrained in place are never
reused (config.json records each checkpoint option's weights)."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from importlib import resources

import pytest
import torch

from policies.evaluation import ConfigMismatch, EvalOptions, run_evaluation
from policies.learned.checkpoint import load_checkpoint, save_checkpoint, weights_digest

SHIPPED = resources.files("policies").joinpath("checkpoints", "riskflow_default.pt")


def _options(out, checkpoint) -> EvalOptions:
    return EvalOptions(
        methods=("bits",),
        scenes=1,
        duration=0.5,
        overrides=(f"bits.checkpoint={checkpoint}",),
        report=False,
        out=str(out),
    )


def _retrain_in_place(path) -> str:
    """Save other weights at ``path`` (as a second training run into the folder would)."""
    checkpoint = load_checkpoint(path)
    state = {name: tensor.clone() for name, tensor in checkpoint["state_dict"].items()}
    name = next(name for name, tensor in state.items() if tensor.is_floating_point())
    state[name] += 1e-3
    save_checkpoint({**checkpoint, "state_dict": state}, path)
    return weights_digest(state)


def test_a_checkpoint_retrained_in_place_is_refused_not_reused(tmp_path):
    generator = tmp_path / "run" / "generator.pt"
    generator.parent.mkdir()
    with resources.as_file(SHIPPED) as shipped:
        shutil.copyfile(shipped, generator)
    out = tmp_path / "eval"
    first = run_evaluation(_options(out, generator), progress=False)
    assert first["ran"] == 1
    recorded = json.loads((out / "config.json").read_text())["checkpoints"]
    assert recorded == {str(generator): torch.load(generator)["weights_sha256"]}

    # the same file again: resumed, nothing re-run
    assert run_evaluation(_options(out, generator), progress=False)["ran"] == 0

    new_digest = _retrain_in_place(generator)
    with pytest.raises(ConfigMismatch, match=r"checkpoint .*generator\.pt with other weights"):
        run_evaluation(_options(out, generator), progress=False)
    # the folder still says which weights its rows are of
    assert json.loads((out / "config.json").read_text())["checkpoints"] == recorded
    # a fresh folder evaluates the new weights
    fresh = tmp_path / "eval_new"
    assert run_evaluation(_options(fresh, generator), progress=False)["ran"] == 1
    assert json.loads((fresh / "config.json").read_text())["checkpoints"] == {
        str(generator): new_digest
    }


def test_a_new_checkpoint_joins_the_folder(tmp_path):
    """A second method option with another checkpoint adds its digest; the first stays."""
    with resources.as_file(SHIPPED) as shipped:
        first, second = tmp_path / "a.pt", tmp_path / "b.pt"
        shutil.copyfile(shipped, first)
        shutil.copyfile(shipped, second)
    out = tmp_path / "eval"
    run_evaluation(_options(out, first), progress=False)
    options = _options(out, first)
    run_evaluation(replace(options, overrides=(f"bits.checkpoint={second}",)), progress=False)
    recorded = json.loads((out / "config.json").read_text())["checkpoints"]
    assert sorted(recorded) == sorted([str(first), str(second)])
    assert len(set(recorded.values())) == 1  # copies of one file: the same weights


def test_a_folder_from_before_digests_resumes_and_records_them(tmp_path):
    """A config.json without ``checkpoints`` (written before they were recorded) resumes;
    the digest is added then."""
    generator = tmp_path / "g.pt"
    with resources.as_file(SHIPPED) as shipped:
        shutil.copyfile(shipped, generator)
    out = tmp_path / "eval"
    run_evaluation(_options(out, generator), progress=False)
    config = json.loads((out / "config.json").read_text())
    del config["checkpoints"]
    (out / "config.json").write_text(json.dumps(config))
    assert run_evaluation(_options(out, generator), progress=False)["ran"] == 0
    assert str(generator) in json.loads((out / "config.json").read_text())["checkpoints"]


def test_a_checkpoint_without_rows_yet_is_recorded_anew(tmp_path):
    """A run stopped before its first row, then the checkpoint retrained: not refused."""
    generator = tmp_path / "g.pt"
    with resources.as_file(SHIPPED) as shipped:
        shutil.copyfile(shipped, generator)
    out = tmp_path / "eval"
    run_evaluation(_options(out, generator), progress=False)
    (out / "results.jsonl").unlink()
    new_digest = _retrain_in_place(generator)
    assert run_evaluation(_options(out, generator), progress=False)["ran"] == 1
    recorded = json.loads((out / "config.json").read_text())["checkpoints"]
    assert recorded == {str(generator): new_digest}


def test_a_checkpoint_changed_during_the_run_stops_it(tmp_path):
    """The workers check the weights the run recorded before each rollout."""
    from policies.evaluation.options import plan_jobs, scene_names
    from policies.evaluation.rollout import job_policy
    from policies.evaluation.runner import checkpoint_digests

    generator = tmp_path / "g.pt"
    with resources.as_file(SHIPPED) as shipped:
        shutil.copyfile(shipped, generator)
    options = _options(tmp_path / "eval", generator)
    jobs = plan_jobs(options, scene_names(options.data, 1))
    digest = checkpoint_digests(jobs)[str(generator)]
    job = replace(jobs[0], checkpoint_sha256=digest)
    job_policy(job)  # unchanged: builds
    _retrain_in_place(generator)
    with pytest.raises(ValueError, match=r"checkpoint .*g\.pt changed during the run"):
        job_policy(job)


def test_the_digest_of_a_checkpoint_without_a_stored_one_is_computed(tmp_path):
    checkpoint = load_checkpoint(SHIPPED)
    old = {k: v for k, v in checkpoint.items() if k not in ("kind", "weights_sha256")}
    torch.save(old, tmp_path / "old.pt")
    from policies.learned.checkpoint import checkpoint_digest

    with pytest.warns(UserWarning, match="no weights_sha256"):
        assert checkpoint_digest(tmp_path / "old.pt") == checkpoint["weights_sha256"]
