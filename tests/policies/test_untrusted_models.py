"""SB3 model files are pickles: loading one needs an explicit opt-in (issue 19 item 4)."""

import pytest

from policies.rl.evaluation import UntrustedModelError, load_ppo_planner

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md


def test_ppo_model_needs_trusted(tmp_path):
    pytest.importorskip("stable_baselines3")
    marker = tmp_path / "marker"
    model = tmp_path / "model.zip"
    model.write_bytes(b"PK not read")
    with pytest.raises(UntrustedModelError, match="trusted=True"):
        load_ppo_planner(str(model))
    assert not marker.exists()


def test_evaluate_ego_runs_needs_trust_model():
    from tests.scripts import load_script

    module = load_script("examples/evaluate_ego.py")
    with pytest.raises(ValueError, match="--trust-model"):
        module.Options(runs="runs/x")
    assert module.Options(runs="runs/x", trust_model=True).trust_model
