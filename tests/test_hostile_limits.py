"""Counts a user sets are bounded (issue 53): a huge ``max_agents``, ``guidance_steps``
or ``--workers`` is refused at once, naming the option and its range, instead of
allocating or running without bound. Each call runs in a child process under a 1.5 GB
address-space cap (:mod:`tests.capped`)."""

from __future__ import annotations

import pytest

from tests.capped import assert_bounded, run_capped

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md

EVAL = "from policies.evaluation.cli import main\n"


@pytest.mark.parametrize(
    ("setup", "call", "error", "fragment"),
    [
        (
            "import riskflow_env; from riskflow_env.config import EnvConfig",
            "riskflow_env.parallel_env(config=EnvConfig(max_agents=100_000))",
            "ValueError",
            "EnvConfig.max_agents must be an int in [1, 1024]",
        ),
        (
            "from policies.riskflow.policy import RiskFlowAdversary",
            "RiskFlowAdversary(guidance_steps=10**9)",
            "ValueError",
            "steps must be an int in [0, 1000]",
        ),
        (
            EVAL,
            "main(['--methods', 'riskflow', '--set', 'riskflow.guidance_steps=1000000000', "
            "'--scenes', '1', '--out', 'never_written'])",
            "SystemExit",
            "steps must be an int in [0, 1000]",
        ),
        (
            EVAL,
            "main(['--methods', 'idm', '--workers', '100000', '--scenes', '1', "
            "'--out', 'never_written'])",
            "SystemExit",
            "--workers must be in [1, 256], got 100000",
        ),
    ],
)
def test_huge_counts_refused_naming_the_option(setup, call, error, fragment, tmp_path):
    outcome = run_capped(f"import os; os.chdir({str(tmp_path)!r})\n{setup}", call)
    assert outcome.error == error, outcome
    assert fragment in (outcome.stderr if error == "SystemExit" else outcome.message), outcome
    assert_bounded(outcome)
    assert not (tmp_path / "never_written").exists()
