"""The checks the command-line tools share, each naming the argument it refuses."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from policies.cli_inputs import check_device, check_interval, check_seeds, parse_seeds
from policies.dataclass_cli import check_at_least, check_choices
from policies.learned.adversary_config import HORIZON_S, check_planning_interval
from riskflow_env.wrappers.video import check_video_path


@dataclass(frozen=True)
class Flags:
    scenes: int | None = 3
    k: int = 0
    mode: str = "fast"


def test_at_least_names_the_flag_and_lets_none_pass_where_optional():
    check_at_least(Flags(scenes=None), {"scenes": 1, "k": 0}, optional=("scenes",))
    for flags, message in (
        (Flags(scenes=None), "--scenes must be an int >= 1, got None"),
        (Flags(scenes=0), "--scenes must be an int >= 1, got 0"),
        (Flags(k=-1), "--k must be an int >= 0, got -1"),
        (Flags(k=True), "--k must be an int >= 0, got True"),
        (Flags(k=1.5), "--k must be an int >= 0, got 1.5"),
    ):
        with pytest.raises(ValueError, match=f"^{message}$"):
            check_at_least(flags, {"scenes": 1, "k": 0})


def test_choices_name_the_flag():
    check_choices(Flags(), {"mode": ("fast", "slow")})
    with pytest.raises(ValueError, match=r"^--mode must be one of \('slow',\), got 'fast'$"):
        check_choices(Flags(), {"mode": ("slow",)})


def test_a_configuration_names_its_field_instead_of_a_flag():
    with pytest.raises(ValueError, match=r"^Flags.scenes must be an int >= 1, got 0$"):
        check_at_least(Flags(scenes=0), {"scenes": 1}, owner="Flags")
    with pytest.raises(ValueError, match=r"^Flags.mode must be one of \('slow',\), got 'fast'$"):
        check_choices(Flags(), {"mode": ("slow",)}, owner="Flags")
    with pytest.raises(ValueError, match=r"^Flags.device: 'nope' is not a torch device"):
        check_device("nope", "Flags.device")


@pytest.mark.parametrize("interval", [0.0, -0.5, 0.25, math.nan, math.inf, -math.inf, 1e-9])
def test_interval_refuses_what_is_not_a_positive_multiple_of_dt(interval):
    with pytest.raises(ValueError, match="^--every: .* s is not a positive multiple of dt"):
        check_interval(interval, 0.1, None, "--every")


def test_interval_rounds_to_the_step_and_keeps_to_the_horizon():
    assert check_interval(0.30000000000000004, 0.1, None) == pytest.approx(0.3)
    assert check_planning_interval(HORIZON_S) == pytest.approx(HORIZON_S)
    with pytest.raises(ValueError, match="^--planning-interval: 5.3 s exceeds the plan horizon"):
        check_planning_interval(5.3)


def test_video_path_names_the_option(tmp_path):
    assert check_video_path(tmp_path / "new" / "a.gif", "--video") == tmp_path / "new" / "a.gif"
    (tmp_path / "file").write_text("")
    (tmp_path / "dir.gif").mkdir()
    for path, message in (
        (tmp_path / "a.txt", "--video must end in one of"),
        (tmp_path / "dir.gif", "--video: .*dir.gif is a folder, not a video file"),
        (tmp_path / "file" / "a.gif", "--video: .*file exists and is not a folder"),
    ):
        with pytest.raises(ValueError, match=message):
            check_video_path(path, "--video")


def test_seeds_one_parser_for_every_tool():
    assert parse_seeds("0,1, 2") == parse_seeds("0 1 2") == check_seeds([0, 1, 2]) == (0, 1, 2)
    assert parse_seeds(str(2**32 - 1)) == (2**32 - 1,)
    taken = check_seeds([np.int64(3), 4])
    assert taken == (3, 4) and all(type(seed) is int for seed in taken)
    for text, message in (
        ("", "--seeds must be comma-separated ints >= 0 (e.g. 0,1,2), got ''"),
        ("0,-1", "--seeds must be comma-separated ints >= 0 (e.g. 0,1,2), got '0,-1'"),
        ("1.5", "--seeds must be comma-separated ints >= 0"),
        ("\u0661", "--seeds must be comma-separated ints >= 0"),  # a non-ASCII digit
        (str(2**32), "--seeds must be one or more ints in [0, 2**32), got [4294967296]"),
        ("3,3", "--seeds must be distinct, got [3, 3]"),
    ):
        with pytest.raises(ValueError) as error:
            parse_seeds(text)
        assert str(error.value).startswith(message)
    for seeds in ((), (True,), (1.0,), (-1,)):
        with pytest.raises(ValueError, match="--train-seeds must be one or more ints"):
            check_seeds(seeds, "--train-seeds")
