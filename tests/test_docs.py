"""Executable documentation: every ```python block and every ```bash block of README.md and
docs/*.md runs, in a scratch folder, in a subprocess.

* Python blocks run as written (``python snippet.py``). A block that reads a ScenarioNet
  sample (``*.pkl``) gets the sample pickles copied in from ``RISKFLOW_SCENARIONET_DIR``
  (default ``../shared/data/scenarionet``); a block (python or bash) that names the
  dataset folder ``sd_nuscenes_mini`` gets them as a ScenarioNet dataset folder there,
  written as ScenarioNet's converter writes one
  (tests/riskflow_env/scenarios/scenarionet_datasets.py), with the user cache in the
  scratch folder. Both are skipped, with that reason, without the samples.
* Bash blocks run as one ``bash -e`` script "at their smallest size": ``SIZES`` rewrites
  every size option the block gives and ``SMALLEST`` adds the size options a command
  leaves at a large default (a later occurrence of an option wins in argparse, so the
  block's own values, themselves rewritten, still apply where they come after). Only
  sizes change; every other option, method list and file path stays as documented.
* The scratch folder links the repository's ``examples/``, ``benchmarks/``, ``docs/``,
  ``tests/``, ``pyproject.toml``, ``mkdocs.yml`` and ``CHANGELOG.md`` and has an empty
  ``policies/checkpoints/``, so
  commands that write (``--out runs/...``, ``cp ... policies/checkpoints/...``) write
  into the scratch folder, never into the repository or the installed package.
* ``INSTEAD`` lists the commands that are not run as such, each with what runs instead.
* A block that needs an optional library (``OPTIONAL``: Ray / RLlib, TorchRL, the interop
  writers), a Python
  block by importing it, a bash block by an option (``OPTIONAL_FLAGS``), is marked
  ``extras`` and skipped, with the extra to install as the reason, where the library
  is missing (``.ci/run`` runs them in its second environment).
* Blocks too slow even at their smallest size are marked ``slow`` (``SLOW``, with why),
  run with ``python -m pytest -m slow``.
* Every test here is in the ``docs`` tier (tests/conftest.py), which the default run leaves
  out: ``python -m pytest -n auto -m docs`` runs it.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from riskflow_env.user_cache import CACHE_ENV
from tests.riskflow_env.scenarios.scenarionet_datasets import write_dataset
from tests.samples import SCENARIONET_DIR

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
SAMPLE_DIR = SCENARIONET_DIR
SAMPLE_DATASET = "sd_nuscenes_mini"  # the samples as a ScenarioNet dataset folder
TIMEOUT = 600  # [s] per block
LINKED = ("examples", "benchmarks", "docs", "tests", "pyproject.toml", "mkdocs.yml", "CHANGELOG.md")

# Size option -> its smallest value. A callable gets the documented values (a list of
# strings) and returns the replacement; lists ("--k 2 3 4 5 10 all", "--seeds 0,1,2")
# keep their first value only.
FIRST = "first"
SIZES: dict[str, str] = {
    "--scenes": "1",  # scenes of a bank / an evaluation
    "--steps": "2",  # training steps (riskflow-train) or episode steps (examples)
    "--workers": "1",
    "--k": FIRST,  # controllable-set sizes (riskflow-eval list)
    "--ks": FIRST,  # benchmarks/adversary_quality.py
    "--interval": FIRST,  # planning intervals (riskflow-eval list)
    "--seeds": FIRST,
    "--total-timesteps": "64",  # PPO
    "--n-steps": "32",  # PPO rollout length
    "--batch-size": "4",  # riskflow-train windows per batch / PPO minibatch
    "--eval-every": "2",  # riskflow-train validation interval [steps]
    "--val-windows": "2",  # riskflow-train validation windows (0 = all)
    "--episodes-per-run": "1",
    "--eval-seeds": FIRST,  # examples/transfer_experiment.py
    "--data-scenes": "1",
    "--episode-steps": "5",
    "--eval-episodes": "1",
    "--duration": "1",  # riskflow-eval episode length [s]
    "--diffusion-steps": "2",  # riskflow-eval DDIM levels of the diffusion methods
    "--time-budget-min": "1",
    "--warmup-steps": "1",  # riskflow-train learning-rate warm-up (< --steps)
    "--copies": "1",  # benchmarks/scenarionet_dataset.py: copies of each scene
    "--batch": FIRST,  # benchmarks/eval_batched.py: --batch-scenes of the batched runs
}

# Program (regex on the command) -> size options added right after it. The first match
# wins; subcommands that take no size (riskflow-eval report / --list) match nothing.
SMALLEST: list[tuple[str, str]] = [
    (
        r"riskflow-eval(?! report| --list)",
        "--scenes 1 --duration 1 --workers 1 --diffusion-steps 2",  # absent: DDPM, 100 levels
    ),
    (r"riskflow-data generate", "--scenes 1 --workers 1"),
    # --warmup-steps and --stop-step: a recipe's own are larger than --steps 2
    (
        r"riskflow-train",
        "--steps 2 --eval-every 2 --val-windows 2 --batch-size 4 --warmup-steps 1 --stop-step 2",
    ),
    (r"python examples/rollout\.py", "--steps 5"),
    (r"python benchmarks/traffic_realism\.py", "--scenes 1 --duration 1"),
    (r"python benchmarks/eval_batched\.py", "--scenes 1 --duration 1 --batch 2"),
    (r"python benchmarks/realism_diagnosis\.py", "--scenes 1"),
    (r"python benchmarks/scenarionet_map_size\.py", "--area 600 --repeats 1 --vehicles 5"),
    (r"python benchmarks/scenarionet_dataset\.py", "--copies 1 --repeats 1 --index-scenes 10"),
    (r"python examples/stress_test_planner\.py", "--scenes 1 --steps 5"),
    (
        r"python benchmarks/ppo_throughput\.py",
        '--decisions 64 --rows recipe vector-shards2 --extra "--scenes 1 --episode-steps 5 '
        '--n-steps 4 --batch-size 8 --n-epochs 1"',
    ),
    (
        r"python examples/train_ego_ppo\.py",
        "--total-timesteps 64 --n-steps 32 --batch-size 32 --scenes 1 --episode-steps 5",
    ),
    (
        r"python examples/evaluate_ego\.py",
        "--scenes 1 --seeds 0 --episodes-per-run 1 --episode-steps 5",
    ),
    (
        r"python examples/transfer_experiment\.py",
        "--scenes 1 --data-scenes 1 --eval-seeds 0 --episode-steps 5 --train-args "
        '"--total-timesteps 64 --n-steps 32 --batch-size 32 --num-envs 2 --scenes 1 '
        '--episode-steps 5 --guidance-steps 2"',
    ),
    (
        r"python examples/train_adversaries_marl\.py",
        "--total-timesteps 64 --n-steps 16 --batch-size 16 --episode-steps 5 --eval-episodes 1",
    ),
]

# Commands replaced, and why.
INSTEAD: dict[str, str] = {
    # Installing needs the network and would change the environment running this test;
    # the test checks that what the command installs is installed.
    'pip install torch==2.13.0 -e ".[dev,rl]"': "python -m pip show riskflow-env",
    'pip install torch==2.13.0 -e ".[dev,rl,fast]"': "python -m pip show riskflow-env numba",
    'pip install -e ".[docs]"': "python -m pip show mkdocs-material mkdocstrings-python",
    # The suite itself, which contains this test: collected, not run again.
    "python -m pytest": "python -m pytest --collect-only -q -p no:cacheprovider",
}

# Blocks marked slow, with why: (file, a command the block runs) -> why. Keyed by content, not
# by the block's index, so that a block added above does not move the mark onto another one.
# Their scripts also have smoke tests in the default run (tests/policies/test_rl.py,
# test_rl_marl.py).
SLOW: dict[tuple[str, str], str] = {
    # The README's 3 RL scripts: about 50 s at their smallest.
    ("README.md", "python examples/train_ego_ppo.py"): "PPO training and evaluation, about 50 s",
    # 9 PPO training / evaluation processes (each loads stable-baselines3 and plays its
    # evaluation episodes against the adversary): about 110 s even at 64 timesteps.
    ("docs/tutorials/rl-ego.md", "python examples/train_ego_ppo.py"): (
        "PPO training and evaluation, about 110 s"
    ),
    # three PPO trainings, then 3 x 5 evaluation traffics: about 100 s at their smallest
    ("docs/tutorials/rl-ego.md", "python examples/transfer_experiment.py"): (
        "three PPO trainings and their evaluation, about 100 s"
    ),
}


def slow(path: Path, code: str) -> bool:
    """Whether the block ``code`` of ``path`` is one of ``SLOW``."""
    name = path.relative_to(ROOT).as_posix()
    return any(name == file and command in code for file, command in SLOW)


# Optional libraries: module -> the extra that installs it (the first match names the extra).
OPTIONAL: dict[str, str] = {
    "ray.rllib": "rllib",
    "ray": "ray",
    "torchrl": "torchrl",
    "scenariogeneration": "interop",
    "commonroad": "interop",
}


# Shell options that need an optional library: option -> its top-level module.
OPTIONAL_FLAGS: dict[str, str] = {
    "--backend ray": "ray",
    "examples/train_ego_torchrl.py": "torchrl",  # the whole script needs it
}


def optional_imports(code: str, language: str = "python") -> list[str]:
    """The ``OPTIONAL`` modules a block needs: those a Python block imports, those the
    options of a bash block run (``OPTIONAL_FLAGS``)."""
    if language == "bash":
        return sorted({module for flag, module in OPTIONAL_FLAGS.items() if flag in code})
    return [
        module
        for module in OPTIONAL
        if re.search(rf"^\s*(?:import|from)\s+{re.escape(module)}\b", code, re.MULTILINE)
    ]


def installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:  # its parent package is missing
        return False


def blocks() -> list[tuple[Path, int, str, str]]:
    """(file, index among its runnable blocks, language, code) of every python / bash block."""
    found = []
    for path in DOCS:
        text = path.read_text(encoding="utf-8")
        matches = re.finditer(r"^```(python|bash)\n(.*?)^```", text, re.DOTALL | re.MULTILINE)
        for index, match in enumerate(matches):
            found.append((path, index, match.group(1), match.group(2)))
    return found


def block_id(path: Path, index: int, language: str, code: str) -> str:
    return f"{path.relative_to(ROOT).as_posix()}-{index}-{language}"


def _first(values: list[str]) -> str:
    return values[0].split(",")[0]


def smallest(script: str) -> str:
    """The bash script with every size option at its smallest value (``SIZES``, ``SMALLEST``)."""
    for command, replacement in INSTEAD.items():
        script = re.sub(rf"(?m)^{re.escape(command)}(?=\s|$)", replacement, script)
    for pattern, options in SMALLEST:
        script = re.sub(pattern, lambda m, o=options: f"{m.group(0)} {o}", script)
    value = r"[^\s\-;&|#\\\"`][^\s;&|#\\\"`]*"
    for option, size in SIZES.items():

        def rewrite(match: re.Match[str], size: str = size) -> str:
            values = match.group(2).split()
            return f"{match.group(1)} {_first(values) if size == FIRST else size}"

        # The option and its values, across line continuations.
        script = re.sub(
            rf"({re.escape(option)})((?:(?:[ \t]|\\\n)+{value})+)(?=\s|$|\\|\"|`)",
            rewrite,
            script,
        )
    return script


def scratch(tmp_path: Path) -> Path:
    for name in LINKED:
        (tmp_path / name).symlink_to(ROOT / name)
    (tmp_path / "policies" / "checkpoints").mkdir(parents=True)
    return tmp_path


def environment(**extra: str) -> dict[str, str]:
    env = dict(os.environ) | extra
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    env["PYTHONDONTWRITEBYTECODE"] = "1"  # nothing written next to the repository's files
    env.setdefault("SDL_VIDEODRIVER", "dummy")
    env.setdefault("MPLBACKEND", "Agg")
    return env


PARAMS = [
    pytest.param(
        path,
        language,
        code,
        id=block_id(path, index, language, code),
        marks=[
            *([pytest.mark.slow] if slow(path, code) else []),
            *([pytest.mark.extras] if optional_imports(code, language) else []),
        ],
    )
    for path, index, language, code in blocks()
]


def test_blocks_are_collected_and_complete() -> None:
    """The collector finds the blocks, and none has a ``...`` placeholder outside comments
    (a new user copies them as they are)."""
    assert len(PARAMS) >= 20, "the collector lost the documentation's code blocks"
    for file, command in SLOW:
        assert any(slow(path, code) for path, _, _, code in blocks() if path == ROOT / file), (
            f"SLOW names a block of {file} that runs {command!r}; there is none"
        )
    for param in PARAMS:
        code = "\n".join(line.split("#")[0] for line in param.values[2].splitlines())
        assert "..." not in code, f"{param.id} has a '...' placeholder:\n{param.values[2]}"


@pytest.mark.parametrize(("path", "language", "code"), PARAMS)
def test_block_runs(path: Path, language: str, code: str, tmp_path: Path) -> None:
    folder = scratch(tmp_path)
    for module in optional_imports(code, language):
        if not installed(module):
            pytest.skip(
                f"{module} is not installed (pip install -e '.[{OPTIONAL[module]}]'): "
                "the block needs it"
            )
    extra = {}
    reads = (language == "python" and ".pkl" in code) or SAMPLE_DATASET in code
    if reads:
        samples = sorted(SAMPLE_DIR.glob("*.pkl")) if SAMPLE_DIR.is_dir() else []
        if not samples:
            pytest.skip(
                f"no ScenarioNet sample pickles in {SAMPLE_DIR}: the snippet reads them;"
                " set RISKFLOW_SCENARIONET_DIR to their folder"
            )
        for sample in samples:
            shutil.copy(sample, folder / sample.name)
        if SAMPLE_DATASET in code:
            write_dataset(folder / SAMPLE_DATASET, samples)
            extra[CACHE_ENV] = str(folder / "user-cache")
    if language == "python":
        (folder / "snippet.py").write_text(code, encoding="utf-8")
        command = [sys.executable, "snippet.py"]
    else:
        (folder / "commands.sh").write_text(smallest(code), encoding="utf-8")
        command = ["bash", "-e", "commands.sh"]
    done = subprocess.run(
        command,
        cwd=folder,
        env=environment(**extra),
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
    )
    assert done.returncode == 0, (
        f"{path.name}: block failed\n--- ran\n{(folder / command[-1]).read_text()}"
        f"\n--- stdout\n{done.stdout[-2000:]}\n--- stderr\n{done.stderr[-4000:]}"
    )
