"""Does training against the adversary transfer? PPO egos trained against three kinds of
traffic, each evaluated in ordinary traffic and under attack, on shipped and recorded scenes.

    python examples/transfer_experiment.py --out runs/transfer --seeds 1,2 \\
        --data ../shared/data/scenarionet

For every seed of ``--seeds`` it trains the target-ego recipe of docs/tutorials/rl-ego.md
(``train_ego_ppo.py`` with the sampling MPC's maneuvers, the batched vector env, 80,000
decisions) three times, with the same budget and seed and only the traffic changed:

* ``adversary``: the RiskFlow adversary, K ramped from 1 to 5, target ``ego`` (the recipe);
* ``unguided``: the unguided generator (K = 0), the same learned traffic without attacks;
* ``idm``: IDM traffic.

A run folder that has a final model is reused, one with checkpoints is resumed
(``train_ego_ppo.py --resume``), so the command picks up where an interrupted one stopped.
Then every trained ego (the policy's mean action) drives the same episodes:

* the shipped evaluation bank (``--scenes`` scenes x ``--eval-seeds``), in the unguided
  generator's traffic and under the adversary (K = 5, target ``ego``);
* with ``--data`` (a ScenarioNet folder or a folder of ``.npz`` scenes: recorded driving),
  the same scenes' log replay, the unguided generator and the adversary.

Each ego's evaluation is saved as its episodes' outcomes in
``<out>/episodes/<traffic>-seed<N>.json`` and not re-run. The report, ``<out>/transfer.md``
(printed) and ``<out>/transfer.json``, has per evaluation traffic and per trained-against
traffic the ego collision rate and off-road rate (Wilson 95% intervals, pooled over seeds)
and the progress [m], then the adversary-trained ego's paired difference in collision rate
against each of the two others on the same episodes (interval and exact McNemar test,
:func:`policies.statistics.paired_difference`). The claim it tests: the adversary-trained
ego collides no more than the others in ordinary traffic, and less under attack.

``--train-args`` is appended to every training command (e.g. a smaller budget:
``--train-args "--total-timesteps 20000"``; the tests run the whole pipeline on a tiny one).
"""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from evaluate_ego import ppo_factory, run_options
from tqdm import tqdm

from policies.cli_inputs import open_data
from policies.dataclass_cli import parse_dataclass
from policies.rl.adversary import AdversaryStage, ScenePolicyConfig
from policies.rl.evaluation import evaluate
from policies.statistics import mean_summary, paired_difference, rate
from policies.stress.summary import progress
from riskflow_env.config import EnvConfig
from riskflow_env.scenarios import shipped_bank

HERE = Path(__file__).resolve().parent
RECIPE = (
    "--vec-env", "batched", "--num-envs", "16", "--n-steps", "64", "--maneuver-set", "mpc",
    "--target-start", "ego", "--target-end", "ego", "--checkpoint-every", "10000",
)  # fmt: skip
TRAINED_AGAINST = {  # name: what train_ego_ppo.py is given besides the recipe
    "adversary": (),
    "unguided": ("--k-start", "0", "--k-end", "0"),
    "idm": ("--traffic", "idm"),
}
ATTACK = ScenePolicyConfig(stage=AdversaryStage(k=5, target="ego"))
TRAFFICS = {  # evaluation traffic: (scene source, traffic)
    "generator": ("shipped", ScenePolicyConfig(stage=AdversaryStage(k=0))),
    "adversary": ("shipped", ATTACK),
    "replay (data)": ("data", ScenePolicyConfig(kind="replay")),
    "generator (data)": ("data", ScenePolicyConfig(stage=AdversaryStage(k=0))),
    "adversary (data)": ("data", ATTACK),
}


@dataclass(frozen=True)
class Options:
    """Options of transfer_experiment.py."""

    out: Path = Path("runs/transfer")
    """the experiment's folder: runs, per-episode outcomes and the report"""
    seeds: str = "1,2"
    """training seeds (each trains three egos)"""
    data: str | None = None
    """recorded scenes to evaluate on too: a ScenarioNet folder or a folder of .npz scenes"""
    scenes: int = 35
    """shipped evaluation scenes, spread evenly over the bank"""
    data_scenes: int = 100
    """at most this many scenes of --data"""
    eval_seeds: str = "0,1,2"
    """traffic seeds of the evaluation episodes (every ego drives the same ones)"""
    episode_steps: int = 100
    """evaluation episode length [steps of 0.1 s]"""
    train_args: str = ""
    """options appended to every train_ego_ppo.py command (they override the recipe's)"""
    trust_model: bool = False
    """load run folders found already trained in --out (SB3 model files are pickles that can
    run code: only for files you trust, docs/reference/security.md); the runs this command
    trains itself need no flag"""

    def __post_init__(self) -> None:
        for name in ("seeds", "eval_seeds"):
            try:
                values = _integers(getattr(self, name))
            except ValueError:
                values = []
            if not values:
                flag, value = name.replace("_", "-"), getattr(self, name)
                raise ValueError(f"--{flag} must be comma-separated integers, got {value!r}")
        if self.scenes < 1 or self.data_scenes < 1 or self.episode_steps < 1:
            raise ValueError("--scenes, --data-scenes and --episode-steps must be >= 1")


def _integers(text: str) -> list[int]:
    return [int(value) for value in text.split(",") if value.strip()]


def train(options: Options, name: str, seed: int) -> Path:
    """The run folder of the ego trained against ``name`` with ``seed`` (trained or resumed
    here unless it has a final model, which needs ``--trust-model``)."""
    run = options.out / name / f"seed{seed}"
    if (run / "final_model.zip").is_file():
        if not options.trust_model:
            raise SystemExit(
                f"transfer_experiment.py: error: {run} is already trained: add --trust-model "
                "to load its model files (pickles that can run code; docs/reference/security.md)"
            )
        return run
    script = str(HERE / "train_ego_ppo.py")
    if (run / "checkpoints").is_dir() and any((run / "checkpoints").iterdir()):
        command = [sys.executable, script, "--resume", str(run)]
    else:
        extra = (*TRAINED_AGAINST[name], *shlex.split(options.train_args))
        command = [sys.executable, script, *RECIPE, *extra, "--seed", str(seed), "--out", str(run)]
    print("$ " + shlex.join(command), flush=True)
    subprocess.run(command, check=True)
    return run


def outcomes(options: Options, name: str, run: Path, scenes: dict) -> dict[str, list]:
    """``{evaluation traffic: [[collided, off-road, progress], ...]}`` of the trained ego of
    ``run`` on every episode (read from its file when an earlier call wrote it)."""
    path = options.out / "episodes" / f"{name}-{run.name}.json"
    if path.is_file():
        return json.loads(path.read_text())
    _, interface = run_options(run)
    factory = ppo_factory(run / "final_model.zip", interface)
    config = EnvConfig(episode_steps=options.episode_steps)
    seeds = _integers(options.eval_seeds)
    labels = [label for label, (source, _) in TRAFFICS.items() if scenes[source]]
    total = len(seeds) * sum(len(scenes[TRAFFICS[label][0]]) for label in labels)
    result = {}
    with tqdm(total=total, desc=f"{name} {run.name}", unit="episode") as bar:
        for label in labels:
            source, traffic = TRAFFICS[label]
            records = evaluate(
                {name: factory}, [traffic], scenes[source], seeds, config, lambda _: bar.update()
            )
            result[label] = [
                [bool(r.metrics["ego_collided"]), bool(r.metrics["ego_offroad"]), progress(r)]
                for r in records[name, traffic.label]
            ]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result))
    return result


def report(results: dict[str, dict[str, list]]) -> tuple[str, dict]:
    """The Markdown table and its JSON of ``{trained against: {traffic: episodes}}``, the
    episodes of every seed concatenated in the same order for every ego."""
    rows, lines = [], _header(
        "evaluated in", "trained against", "ego collision rate", "off-road rate",
        "progress [m]", "episodes",
    )  # fmt: skip
    pairs, pair_lines = [], _header(
        "evaluated in", "adversary-trained minus", "collision rate difference [95%]",
        "p (McNemar)", "episodes",
    )  # fmt: skip
    for traffic in TRAFFICS:
        episodes = {n: np.array(r[traffic], float) for n, r in results.items() if traffic in r}
        for name, values in episodes.items():
            entry = {
                "traffic": traffic,
                "trained_against": name,
                "ego_collision_rate": rate(int(values[:, 0].sum()), len(values)),
                "ego_offroad_rate": rate(int(values[:, 1].sum()), len(values)),
                "progress": mean_summary(values[:, 2].tolist()),
            }
            rows.append(entry)
            cells = [_rate(entry["ego_collision_rate"]), _rate(entry["ego_offroad_rate"])]
            lines.append(f"| {traffic} | {name} | {' | '.join(cells)} | "
                         f"{entry['progress']['value']:.1f} | {len(values)} |")  # fmt: skip
        if "adversary" not in episodes:
            continue
        ours = episodes["adversary"][:, 0].astype(bool)
        for name, values in episodes.items():
            if name == "adversary" or len(values) != len(ours):
                continue
            theirs = values[:, 0].astype(bool)
            counts = {
                "n": len(ours),
                "trained": int(ours.sum()),
                "untrained": int(theirs.sum()),
                "trained_only": int((ours & ~theirs).sum()),
                "untrained_only": int((~ours & theirs).sum()),
            }
            diff = paired_difference(counts)
            pairs.append({"traffic": traffic, "against": name, **diff})
            pair_lines.append(
                f"| {traffic} | {name} | {diff['difference']:+.3f} "
                f"[{diff['low']:+.3f}, {diff['high']:+.3f}] | {diff['p_value']:.3g} | {len(ours)} |"
            )
    text = "\n".join(lines) + "\n\nPaired, same episodes:\n\n" + "\n".join(pair_lines)
    return text, {"rows": rows, "paired": pairs}


def _header(*names: str) -> list[str]:
    return ["| " + " | ".join(names) + " |", "|" + " --- |" * len(names)]


def _rate(entry: dict) -> str:
    return f"{entry['value']:.3f} [{entry['low']:.3f}, {entry['high']:.3f}]"


def main(argv: list[str] | None = None) -> None:
    options = parse_dataclass(
        Options, argv, prog="transfer_experiment.py", description=__doc__.split("\n")[0]
    )
    try:
        data = open_data(options.data) if options.data is not None else []
    except ValueError as error:
        print(f"transfer_experiment.py: error: {error}", file=sys.stderr)
        sys.exit(2)
    bank = shipped_bank("eval")
    count = min(options.scenes, len(bank))
    scenes = {
        "shipped": [bank[round(i * len(bank) / count)] for i in range(count)],
        "data": [data[i] for i in range(min(options.data_scenes, len(data)))],
    }
    runs = {(name, seed): train(options, name, seed)
            for seed in _integers(options.seeds) for name in TRAINED_AGAINST}  # fmt: skip
    results: dict[str, dict[str, list]] = {}
    for (name, _), run in runs.items():  # seeds in order: episodes line up across egos
        for traffic, episodes in outcomes(options, name, run, scenes).items():
            results.setdefault(name, {}).setdefault(traffic, []).extend(episodes)
    text, content = report(results)
    (options.out / "transfer.md").write_text(text + "\n")
    (options.out / "transfer.json").write_text(json.dumps(content, indent=1))
    print(text)
    print(f"\nwritten: {options.out / 'transfer.md'}, {options.out / 'transfer.json'}")


if __name__ == "__main__":
    main()
