"""riskflow-eval: results file, resuming, determinism, workers, report, argument errors."""

from __future__ import annotations

import importlib.util
import json
import math
import re
from dataclasses import replace

import pytest
import torch

from policies.evaluation import (
    METHODS,
    ConfigMismatch,
    EvalOptions,
    ResultsStore,
    build_policy,
    run_evaluation,
    write_report,
)
from policies.evaluation.cli import main
from policies.evaluation.options import check_device
from policies.evaluation.report import _mean_first_time, build_tables, safety_metric
from policies.evaluation.rollout import HISTORY
from policies.riskflow.guidance import GuidanceConfig
from riskflow_env.view import ScenePolicy

# tiny: 2 scenes, 1 s episodes, RiskFlow with a 2-step guidance budget
TINY = EvalOptions(
    methods=("idm", "replay", "riskflow"),
    k=("2",),
    interval=(0.5,),
    scenes=2,
    duration=1.0,
    overrides=("riskflow.guidance_steps=2",),
    report=False,
)
VOLATILE = ("timing", "samples")  # wall times and file names differ between runs


def _numbers(out) -> dict[str, dict]:
    rows = ResultsStore(out).rows()
    return {row["key"]: {k: v for k, v in row.items() if k not in VOLATILE} for row in rows}


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("eval") / "full"
    summary = run_evaluation(replace(TINY, out=str(out)), progress=False)
    return out, summary


def test_results_rows_and_schema(tiny_run):
    out, summary = tiny_run
    assert summary == summary | {"planned": 6, "skipped": 0, "ran": 6}
    rows = ResultsStore(out).rows()
    assert len(rows) == 6 and len({row["key"] for row in rows}) == 6
    row = next(r for r in rows if r["method"] == "riskflow")
    assert row["k"] == 2 and row["interval"] == 0.5 and row["steps"] == 10
    assert row["options"] == {"guidance_steps": 2}
    assert row["label"] == "riskflow[guidance_steps=2]"
    for key in ("collision", "ego_collision", "offroad_centroid_steps", "ade", "fde"):
        assert key in row
    assert row["timing"]["planning_cycles"] == 2 and row["timing"]["cycle_ms_mean"] > 0
    assert 0.0 <= row["wosac"]["metametric"] <= 1.0
    assert (out / row["samples"]).is_file()
    idm = next(r for r in rows if r["method"] == "idm")
    assert idm["k"] is None and idm["interval"] is None  # one run serves every table


@pytest.mark.reliability
def test_resume_skips_finished_rows_and_keeps_numbers(tiny_run, tmp_path):
    full, _ = tiny_run
    out = tmp_path / "resumed"
    # an "interrupted" run: a subset of the rollouts, then a torn last line
    first = run_evaluation(replace(TINY, out=str(out), methods=("idm",), scenes=1), progress=False)
    assert first["ran"] == 1
    with open(out / "results.jsonl", "ab") as file:
        file.write(b'{"key": "half a line')
    second = run_evaluation(replace(TINY, out=str(out)), progress=False)
    assert (second["skipped"], second["ran"]) == (1, 5)
    again = run_evaluation(replace(TINY, out=str(out)), progress=False)
    assert again["ran"] == 0
    assert _numbers(out) == _numbers(full)  # nothing duplicated, same numbers


@pytest.mark.reliability
def test_worker_count_does_not_change_results(tiny_run, tmp_path):
    full, _ = tiny_run
    out = tmp_path / "workers"
    options = replace(TINY, out=str(out), methods=("riskflow", "idm"), workers=2)
    run_evaluation(options, progress=False)
    expected = {k: v for k, v in _numbers(full).items() if v["method"] in ("riskflow", "idm")}
    assert _numbers(out) == expected


@pytest.mark.extras
@pytest.mark.skipif(
    importlib.util.find_spec("ray") is None,
    reason="ray is not installed (pip install -e '.[ray]'; .ci/run installs it)",
)
def test_ray_backend_gives_the_local_results_and_resumes(tiny_run, tmp_path):
    """--backend ray on a local Ray with 2 CPUs: the same rows, bit for bit, as the local
    backend; a second run finds them all in the results file."""
    full, _ = tiny_run
    out = tmp_path / "ray"
    options = replace(TINY, out=str(out), methods=("riskflow", "idm"), workers=2, backend="ray")
    assert run_evaluation(options, progress=False)["ran"] == 4
    expected = {k: v for k, v in _numbers(full).items() if v["method"] in ("riskflow", "idm")}
    assert _numbers(out) == expected
    assert run_evaluation(options, progress=False)["ran"] == 0


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"backend": "dask"}, "--backend must be one of"),
        ({"address": "auto"}, "--address is a Ray cluster address"),
    ],
)
def test_bad_backend_names_the_argument(changes, message, tmp_path):
    with pytest.raises(ValueError, match=message):
        run_evaluation(replace(TINY, out=str(tmp_path / "bad"), **changes), progress=False)


@pytest.mark.reliability
def test_config_mismatch_is_refused(tiny_run):
    out, _ = tiny_run
    with pytest.raises(ConfigMismatch, match="ego"):
        run_evaluation(replace(TINY, out=str(out), ego="constant_velocity"), progress=False)


def test_report(tiny_run):
    out, _ = tiny_run
    path = write_report(out)
    text = path.read_text()
    assert "## K=2, T=0.5 s (2 rollouts a method: scene x seed pairs)" in text
    assert "| riskflow[guidance_steps=2] | 2 |" in text and "| idm | 2 |" in text
    for name in ("cs_rs_T0.5.png", "speed.png"):
        assert (out / name).stat().st_size > 0
        assert f"({name})" in text
    assert "realism_vs_horizon" not in text  # one planning interval: no line to draw


def test_report_leaves_reference_traffic_out_of_the_scores(tiny_run):
    """IDM traffic and replay are shown with their raw metrics but outside the CS / RS
    normalisation ('ref.'); CS normalises SCR unless the target is the ego."""
    out, _ = tiny_run
    (table,) = build_tables(ResultsStore(out))
    assert table.references == {"idm", "replay"} and table.safety_metric == "scr"
    assert math.isnan(table.metrics["idm"]["cs"]) and math.isnan(table.metrics["replay"]["rs"])
    guided = table.metrics["riskflow[guidance_steps=2]"]
    assert guided["cs"] == 0.0 and guided["rs"] == 1.0  # the only generator: degenerate
    text = write_report(out, plots=False).read_text()
    assert "| TTFC [s] | ego TTFC [s] |" in text
    idm_row = next(line for line in text.splitlines() if line.startswith("| idm |"))
    assert idm_row.endswith("| ref. | ref. |")
    assert safety_metric("ego") == "ego_collision_rate" and safety_metric("others") == "scr"


def test_the_horizon_plot_needs_several_intervals(tmp_path):
    """A realism-against-interval line per K only where a K has several intervals."""
    from policies.evaluation.plots import write_plots
    from policies.evaluation.report import METRIC_COLUMNS
    from policies.evaluation.table import Table

    metrics = {"riskflow": {key: 0.5 for key, _ in METRIC_COLUMNS}}
    timing = {"riskflow": {"total_s": 1.0, "per_scene_s": 1.0, "cycle_ms": 50.0}}
    tables = [Table(5, interval, 2, metrics, timing) for interval in (0.5, 1.0)]
    tables.append(Table(2, 0.5, 2, metrics, timing))
    names = {path.name for path in write_plots(tables, tmp_path)}
    assert "realism_vs_horizon_K5.png" in names and "realism_vs_horizon_K2.png" not in names
    assert all((tmp_path / name).stat().st_size > 0 for name in names)


def test_first_collision_times_are_after_the_start():
    """Record steps count ``HISTORY`` logged steps and the start state as context: the
    first simulated step is 0.1 s; rollouts without a collision are left out."""
    assert _mean_first_time([HISTORY + 1.0, HISTORY + 3.0, -1.0]) == pytest.approx(0.2)
    assert math.isnan(_mean_first_time([-1.0])) and math.isnan(_mean_first_time([math.nan]))


def test_report_command(tiny_run, capsys):
    out, _ = tiny_run
    main(["report", "--out", str(out), "--no-plots"])
    assert "report.md" in capsys.readouterr().out


@pytest.mark.reliability
@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--methods", "nope"], "--methods: unknown method 'nope'"),
        (["--methods", "riskflw"], "unknown method 'riskflw' (did you mean riskflow?); known:"),
        (["--k", "-1"], "--k: expected an int >= 0"),
        (["--k", "two"], "--k: expected an int >= 0"),
        (["--interval", "0.55"], "--interval: 0.55 s is not a positive multiple"),
        (["--interval", "9.0"], "--interval: 9.0 s exceeds the plan horizon"),
        (["--ego", "pilot"], "--ego must be one of"),
        (["--ego", "my_planner.py:plan"], "own runs with riskflow-stress --planner"),
        (["--target", "all"], "--target must be one of"),
        (["--duration", "1.05"], "--duration"),
        (["--scenes", "0"], "--scenes must be an int >= 1, got 0"),
        (["--set", "riskflow.warp=3"], "'warp' is not an option of riskflow"),
        (["--set", "guidance_steps"], "--set: expected key=value"),
        (["--set", "ctg.guidance_steps=3"], "'guidance_steps' is not an option of ctg"),
        (["--set", "nope.steps=3"], "unknown method 'nope'"),
        (["--set", "target=ego"], "--set 'target=ego': target is set by --target"),
        (["--set", "riskflow.k=3"], "k is set by --k, for every method"),
        (
            ["--set", "riskflow.stepsize=0.1"],
            "'stepsize' is not an option of riskflow (did you mean step_size?); its options: ",
        ),
        (["--set", "stepsize=0.1"], "(did you mean step_size?); their options: avoid_step_size"),
        (["--set", "riskflow.lambda_map=-1"], "--methods riskflow"),
        (["--data", "/nonexistent/dir"], "--data"),
        (["--seeds", "0", "-1"], "--seeds must be one or more ints in [0, 2**32), got [0, -1]"),
        (["--seeds", "1", "1"], "--seeds must be distinct, got [1, 1]"),
        (["--device", "nope"], "--device: 'nope' is not a torch device"),
        (["--device", "meta"], "--device: 'meta' is not supported"),
        (["--scenes", "1000"], "--scenes 1000: the shipped evaluation bank holds only"),
    ],
)
def test_bad_arguments_name_the_argument(argv, message, tmp_path, capsys):
    scenes = [] if "--scenes" in argv else ["--scenes", "1"]
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, *scenes, "--out", str(tmp_path / "bad")])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


@pytest.mark.reliability
@pytest.mark.parametrize(
    "argv", [["--seeds", "-1"], ["--device", "nope"], ["--scenes", "1000"], ["--k", "-1"]]
)
def test_bad_arguments_write_nothing(argv, tmp_path, capsys):
    """Issue 19: `--seeds -1` wrote config.json, then died in a worker with a traceback."""
    out = tmp_path / "out"
    scenes = [] if "--scenes" in argv else ["--scenes", "1"]
    with pytest.raises(SystemExit) as exit_info:
        main(["--methods", "idm", *argv, *scenes, "--out", str(out)])
    assert exit_info.value.code == 2
    assert argv[0] in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.reliability
@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"workers": 0}, "--workers must be in [1, 256], got 0"),
        ({"workers": 2.0}, "--workers must be an int, got 2.0"),
        ({"duration": -1.0}, "--duration: -1.0 s is not a positive multiple of dt = 0.1 s"),
        ({"duration": 1e12}, "--duration: 1e+12 s is over the longest episode, 1e+06 s"),
        ({"seeds": (-1,)}, "--seeds must be one or more ints in [0, 2**32), got [-1]"),
        ({"methods": ()}, "--methods: give at least one method"),
        ({"methods": ("idm", "idm")}, "--methods: repeated method in ('idm', 'idm')"),
        ({"k": ()}, "--k: give at least one value"),
        ({"k": ("two",)}, "--k: expected an int >= 0 or 'all', got 'two'"),
        ({"interval": (0.55,)}, "--interval: 0.55 s is not a positive multiple of dt"),
        ({"scenes": 0}, "--scenes must be an int >= 1, got 0"),
        ({"diffusion_steps": 0}, "--diffusion-steps must be an int >= 1, got 0"),
        ({"batch_scenes": 0}, "--batch-scenes must be an int >= 1, got 0"),
        ({"backend": "dask"}, "--backend must be one of ('local', 'ray'), got 'dask'"),
        ({"ego": "pilot"}, "--ego must be one of"),
        ({"target": "all"}, "--target must be one of ('others', 'ego'), got 'all'"),
        ({"device": "nope"}, "--device: 'nope' is not a torch device"),
    ],
)
def test_bad_values_are_refused_when_the_options_are_built(changes, message):
    """Every value is checked by ``EvalOptions`` itself, not first when the run starts."""
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        EvalOptions(**changes)


@pytest.mark.reliability
def test_out_that_is_a_file_names_the_argument(tmp_path, capsys):
    existing = tmp_path / "results.txt"
    existing.write_text("keep me")
    for out in (existing, existing / "sub"):
        with pytest.raises(SystemExit) as exit_info:
            main(["--methods", "idm", "--scenes", "1", "--out", str(out)])
        assert exit_info.value.code == 2
        assert f"--out: {existing} exists and is not a folder" in capsys.readouterr().err
    assert existing.read_text() == "keep me"


@pytest.mark.reliability
def test_cuda_device_without_cuda_names_the_argument():
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    with pytest.raises(ValueError, match="--device cuda: CUDA is not available"):
        check_device("cuda")


def test_list(capsys):
    main(["--list"])
    listed = capsys.readouterr().out
    assert all(name in listed for name in METHODS)


@pytest.mark.parametrize("name", sorted(METHODS))
def test_every_method_builds(name):
    policy = build_policy(name, {}, k=2, planning_interval=0.5, target="others", seed=0)
    assert isinstance(policy, ScenePolicy)


def test_guidance_step_defaults():
    """RiskFlow guides with the target's step : 0.01
    with the paper's target, 0.1 with target ``ego``; STRIVE-style with its own best, 0.1, for
    either; ``--set`` overrides each."""

    def build(name, target="others", **options):
        policy = build_policy(name, options, k=2, planning_interval=0.5, target=target, seed=0)
        return policy.guidance.resolved_step_size

    assert build("riskflow") == 0.01
    assert build("riskflow", target="ego") == 0.1
    assert build("riskflow-nosep") == 0.01
    assert build("strive") == 0.1
    assert build("strive", target="ego") == 0.1
    assert build("riskflow", step_size=0.1) == 0.1
    assert build("riskflow", target="ego", step_size=0.03) == 0.03
    assert build("strive", step_size=0.3) == 0.3
    # a curriculum that switches the target (policies.rl.adversary.apply_stage) switches
    # the default step with it; a given step stays
    default = build_policy("riskflow", {}, k=2, planning_interval=0.5, target="others", seed=0)
    assert replace(default.guidance, target="ego").resolved_step_size == 0.1
    given = GuidanceConfig(step_size=0.05)
    assert replace(given, target="ego").resolved_step_size == 0.05


@pytest.mark.reliability
def test_rows_are_json_without_nan(tiny_run):
    out, _ = tiny_run
    for line in (out / "results.jsonl").read_text().splitlines():
        json.loads(line, parse_constant=lambda name: pytest.fail(f"{name} in results"))


def test_cs_rs_markers_on_one_point_are_spread():
    from policies.evaluation.plots import SPREAD, spread

    placed = spread({"ctg": (0.0, 1.0), "ctgpp": (0.001, 1.0), "idm": (0.7, 0.0)})
    assert placed["idm"] == (0.7, 0.0)
    assert placed["ctgpp"][0] - placed["ctg"][0] == pytest.approx(SPREAD)
    assert placed == spread({"ctg": (0.0, 1.0), "ctgpp": (0.001, 1.0), "idm": (0.7, 0.0)})


def test_cs_rs_markers_never_overlap_after_the_spread():
    """A row of methods at CS = 1 (the K=10 panel of docs/results/ksweep): chains of near
    points are laid out as one group, so no marker lands on another group's."""
    import itertools
    import math

    from policies.evaluation.plots import SPREAD, spread

    rs = {"ccdiff": 0.09, "ctg": 0.13, "ctgpp": 0.168, "riskflow": 0.192, "strive": 0.23}
    placed = spread({label: (x, 1.0) for label, x in rs.items()} | {"bits": (0.48, 0.75)})
    for a, b in itertools.combinations(placed, 2):
        assert math.dist(placed[a], placed[b]) >= SPREAD - 1e-12, (a, b)
    assert [label for label, _ in sorted(placed.items(), key=lambda kv: kv[1][0])][:5] == [
        *rs
    ]  # the order along RS is kept
    assert placed["bits"] == (0.48, 0.75)


@pytest.mark.reliability
def test_data_that_is_not_a_scene_folder_names_the_argument(tmp_path, capsys):
    pickled = tmp_path / "scene.pkl"
    pickled.write_bytes(b"")
    with pytest.raises(SystemExit):
        main(["--data", str(pickled), "--methods", "idm", "--out", str(tmp_path / "out")])
    error = capsys.readouterr().err
    assert "--data:" in error and "is a file" in error and "load_scenarionet" in error


def test_leave_when_log_ends_reaches_the_env_and_the_config(tmp_path):
    """--leave-when-log-ends: the env lets vehicles leave when their log ends; the run's
    config.json records it (only when set: runs made before the option still resume),
    and a run with it does not resume one without."""
    from policies.evaluation.options import RunConfig

    leave = RunConfig.from_options(replace(TINY, leave_when_log_ends=True))
    stay = RunConfig.from_options(TINY)
    assert (
        leave.env_config(0.1).leave_when_log_ends and not stay.env_config(0.1).leave_when_log_ends
    )
    assert leave.as_json()["leave_when_log_ends"] is True
    assert "leave_when_log_ends" not in stay.as_json()
    out = tmp_path / "run"
    options = replace(TINY, methods=("replay",), scenes=1, out=str(out))
    run_evaluation(replace(options, leave_when_log_ends=True), progress=False)
    with pytest.raises(ConfigMismatch):
        run_evaluation(options, progress=False)
