"""``evaluate_ego.py --combine``: disjoint evaluations pool, the same episodes twice do not."""

from __future__ import annotations

import json

import pytest

from policies.rl.combine import load_results
from policies.rl.runs import RunError

METRICS = ("ego_collision_rate", "ego_offroad_rate", "ego_failure_rate", "progress")
TRAFFIC = "riskflow K=5"
SCENES = ["highway-eval-s0-00000", "merge-eval-s0-00001"]


def _row(planner: str, rate: float, n: int = 10) -> dict:
    entry = {"value": rate, "low": 0.0, "high": 1.0, "n": n}
    return {"planner": planner, "traffic": TRAFFIC} | dict.fromkeys(METRICS, entry)


def _results(tmp_path, name, seed, baseline_seeds=(0, 1, 2), recorded=True) -> str:
    """A results.json of one PPO run (training seed ``seed``, episode seeds ``seed * 100 +
    i``) and the IDM ego on ``baseline_seeds`` (none when empty)."""
    runs = {f"ppo (seed {seed})": [seed * 100, seed * 100 + 1]}
    runs[f"ppo-initial (seed {seed})"] = runs[f"ppo (seed {seed})"]
    summary = [_row("ppo", 0.2), _row("ppo-initial", 0.5)]
    summary += [_row("idm", 0.3)] if baseline_seeds else []
    per_run = [_row(planner, 0.2) for planner in runs]
    seeds = runs | ({"idm": list(baseline_seeds)} if baseline_seeds else {})
    content = {"summary": summary, "per_run": per_run, "paired": [], "mask_actions": True}
    content["episodes"] = {"scenes": SCENES, "seeds": seeds} if recorded else None
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(content))
    return str(path)


def test_two_runs_pool_and_so_does_a_baseline_on_other_seeds(tmp_path):
    first = _results(tmp_path, "a", seed=0)
    second = _results(tmp_path, "b", seed=1, baseline_seeds=(3, 4))
    summaries, per_run, _, mask, episodes = load_results(f"{first},{second}")
    assert summaries["ppo", TRAFFIC]["ego_collision_rate"]["n"] == 20
    assert summaries["idm", TRAFFIC]["ego_collision_rate"]["n"] == 20
    assert len(per_run) == 4 and mask is True
    assert episodes["seeds"]["idm"] == [0, 1, 2, 3, 4] and episodes["scenes"] == SCENES


def test_the_same_episodes_twice_are_refused(tmp_path):
    first = _results(tmp_path, "a", seed=0)
    with pytest.raises(RunError, match="names .*a.json twice"):
        load_results(f"{first},{first}")
    same_run = _results(tmp_path, "c", seed=0, baseline_seeds=())
    with pytest.raises(RunError, match=r"ppo \(seed 0\) drove the same episodes .*\[0, 1\]"):
        load_results(f"{first},{same_run}")
    same_baseline = _results(tmp_path, "d", seed=1, baseline_seeds=(2, 5))
    with pytest.raises(RunError, match=r"idm drove the same episodes .*seeds \[2\]"):
        load_results(f"{first},{same_baseline}")


def test_files_without_their_episodes_pool_as_they_are(tmp_path):
    first = _results(tmp_path, "a", seed=0, recorded=False)
    second = _results(tmp_path, "b", seed=1)
    summaries, *_, episodes = load_results(f"{first},{second}")
    assert summaries["idm", TRAFFIC]["ego_collision_rate"]["n"] == 20 and episodes is None
