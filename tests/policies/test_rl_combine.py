"""``evaluate_ego.py --combine``: disjoint evaluations pool, the same episodes twice do not."""

from __future__ import annotations

import json

import pytest

from policies.rl.combine import load_results
from policies.rl.runs import RunError

METRICS = ("ego_collision_rate", "ego_offroad_rate", "ego_failure_rate", "progress")
TRAFFIC = "riskflow K=5"


def _row(planner: str, rate: float, n: int = 10) -> dict:
    entry = {"value": rate, "low": 0.0, "high": 1.0, "n": n}
    return {"planner": planner, "traffic": TRAFFIC} | dict.fromkeys(METRICS, entry)


def _results(tmp_path, name: str, seed: int, baselines: bool = True) -> str:
    """A results.json of one PPO run (training seed ``seed``), with the IDM ego or not."""
    summary = [_row("ppo", 0.2), _row("ppo-initial", 0.5)]
    summary += [_row("idm", 0.3)] if baselines else []
    per_run = [_row(f"ppo (seed {seed})", 0.2), _row(f"ppo-initial (seed {seed})", 0.5)]
    path = tmp_path / f"{name}.json"
    content = {"summary": summary, "per_run": per_run, "paired": [], "mask_actions": True}
    path.write_text(json.dumps(content))
    return str(path)


def test_two_runs_pool_and_their_baselines_count_once(tmp_path):
    first = _results(tmp_path, "a", seed=0)
    second = _results(tmp_path, "b", seed=1, baselines=False)
    summaries, per_run, _, mask = load_results(f"{first},{second}")
    assert summaries["ppo", TRAFFIC]["ego_collision_rate"]["n"] == 20
    assert summaries["idm", TRAFFIC]["ego_collision_rate"]["n"] == 10
    assert len(per_run) == 4 and mask is True


def test_the_same_episodes_twice_are_refused(tmp_path):
    first = _results(tmp_path, "a", seed=0)
    with pytest.raises(RunError, match="names .*a.json twice"):
        load_results(f"{first},{first}")
    same_seed = _results(tmp_path, "c", seed=0, baselines=False)
    with pytest.raises(RunError, match=r"rows of ppo \(seed 0\) under riskflow K=5 are in two"):
        load_results(f"{first},{same_seed}")
    both_baselines = _results(tmp_path, "d", seed=1)
    with pytest.raises(RunError, match="idm under riskflow K=5 is in .*a.json and .*d.json"):
        load_results(f"{first},{both_baselines}")
