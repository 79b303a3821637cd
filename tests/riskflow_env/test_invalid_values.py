"""Invalid values are refused at the boundary with an error naming the field (issue 19 item 3)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from riskflow_env.config import DynamicsConfig, EnvConfig, ObservationConfig
from riskflow_env.scenarios import ScenarioFormatError, load_scenario, save_scenario
from riskflow_env.wrappers import EgoEnv

pytestmark = pytest.mark.reliability  # docs/reference/reliability.md

_spec = importlib.util.spec_from_file_location(
    "_io_tests", Path(__file__).parent / "scenarios" / "test_io.py"
)
_io = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_io)
_env_spec = importlib.util.spec_from_file_location(
    "_env_tests", Path(__file__).with_name("test_env.py")
)
_env = importlib.util.module_from_spec(_env_spec)
_env_spec.loader.exec_module(_env)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"max_agents": True}, "max_agents"),
        ({"max_agents": 2.0}, "max_agents"),
        ({"episode_steps": False}, "episode_steps"),
        ({"clip_actions": 1}, "clip_actions"),
        ({"observation": {"num_neighbors": 2}}, "observation"),
    ],
)
def test_env_config_types(kwargs, field):
    with pytest.raises(ValueError, match=f"EnvConfig.{field}"):
        EnvConfig(**kwargs)


def test_termination_options_name_the_field_and_lists_become_tuples():
    for value in (5, None, ("ego", 3)):
        with pytest.raises(ValueError, match="EnvConfig.terminate_on_collision must be one of"):
            EnvConfig(terminate_on_collision=value)
    config = EnvConfig(terminate_on_collision=["ego"])
    assert config.terminate_on_collision == ("ego",) and hash(config) == hash(
        EnvConfig(terminate_on_collision=("ego",))
    )
    names = EnvConfig(terminate_on_collision={"ego", "agent_1"}).terminate_on_collision
    assert names == ("agent_1", "ego")


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"num_vehicles": 5}, "TrafficConfig.num_vehicles must be a pair (min, max), got 5"),
        ({"num_vehicles": (3, 2)}, "TrafficConfig.num_vehicles must satisfy 1 <= min <= max"),
        ({"num_vehicles": (1.5, 3)}, "TrafficConfig.num_vehicles must be an int in [1, "),
        ({"length_range": (4.0, "x")}, "TrafficConfig.length_range must be a finite number"),
        ({"dt": float("inf")}, "TrafficConfig.dt must be a finite number"),
        ({"future_steps": 2.0}, "TrafficConfig.future_steps must be an int, got 2.0"),
    ],
)
def test_traffic_config_values(kwargs, message):
    from riskflow_env.scenarios.traffic import TrafficConfig

    with pytest.raises(ValueError) as error:
        TrafficConfig(**kwargs)
    assert str(error.value).startswith(message)


@pytest.mark.parametrize("number", [np.float32(0.1), np.float16(0.1), np.float64(0.1)])
def test_numpy_float_scalars_are_numbers(number):
    """np.float32(0.1) was refused as dt ("must be a finite number"); numpy float scalars
    of any dtype are numbers, stored as Python floats (float32 0.1 as 0.1)."""
    from riskflow_env.config import RewardConfig, is_number
    from riskflow_env.scenarios.traffic import TrafficConfig

    values = [
        DynamicsConfig(dt=number).dt,
        TrafficConfig(dt=number, length_range=(4.0, number * 50)).dt,
        TrafficConfig(length_range=(number * 40, 5.0)).length_range[0] / 40,
        RewardConfig(speed=number).speed,
        ObservationConfig(ray_distances=(number, 5.0)).ray_distances[0],
        _io._scenario(dt=number).dt,
    ]
    assert all(type(value) is float and value == pytest.approx(0.1, abs=1e-15) for value in values)
    assert DynamicsConfig(dt=np.float32(0.1)) == DynamicsConfig(dt=0.1)
    assert is_number(np.int64(3)) and not is_number(np.bool_(True))


def test_numpy_integers_are_ints():
    """np.int64(8) was refused where a config or an argument takes an int; numpy integers
    are ints, stored as Python ints; numpy bools are still refused."""
    from policies.baselines.diffusion.schedule import ScheduleConfig
    from policies.dataclass_cli import check_at_least
    from policies.learned.config import ModelConfig
    from policies.learned.windows import WindowConfig
    from policies.riskflow.guidance_scene import GuidanceConfig
    from policies.stress.episode import EpisodeSetup
    from policies.stress.escape import EscapeSearch
    from policies.stress.runner import StressOptions
    from riskflow_env.config import is_integer
    from riskflow_env.render import RenderConfig
    from riskflow_env.scenarios.naturalistic import SceneConfig
    from riskflow_env.scenarios.traffic import TrafficConfig

    values = [
        EnvConfig(max_agents=np.int64(8)).max_agents,
        EnvConfig(episode_steps=np.int32(8)).episode_steps,
        ObservationConfig(num_neighbors=np.int16(8)).num_neighbors,
        TrafficConfig(num_vehicles=(np.int64(8), 9)).num_vehicles[0],
        TrafficConfig(future_steps=np.uint8(8)).future_steps,
        RenderConfig(width_px=np.int64(8 * 16)).width_px // 16,
        ScheduleConfig(num_steps=np.int64(8)).num_steps,
        EscapeSearch(samples=np.int64(8)).samples,
        EpisodeSetup(steps=np.int64(8)).steps,
        StressOptions(scenes=np.int64(8)).scenes,  # check_at_least on a frozen dataclass
        WindowConfig(max_agents=np.int64(8)).max_agents,
        GuidanceConfig(steps=np.int64(8)).steps,
        ModelConfig(map_widths=(np.int64(8),)).map_widths[0],
        SceneConfig(future_steps=np.int64(8)).future_steps,
    ]
    assert all(type(value) is int and value == 8 for value in values)

    class Options:
        workers = np.int64(2)

    options = Options()
    check_at_least(options, {"workers": 1})
    assert type(options.workers) is int and options.workers == 2
    assert not is_integer(np.bool_(True)) and not is_integer(2.0)
    with pytest.raises(ValueError, match="EnvConfig.max_agents"):
        EnvConfig(max_agents=np.bool_(True))


@pytest.mark.parametrize("flag", [True, np.bool_(True)])
def test_bools_are_not_numbers(flag):
    from riskflow_env.config import RewardConfig
    from riskflow_env.scenarios.traffic import TrafficConfig

    for build, field in (
        (lambda: DynamicsConfig(dt=flag), "DynamicsConfig.dt"),
        (lambda: TrafficConfig(dt=flag), "TrafficConfig.dt"),
        (lambda: RewardConfig(speed=flag), "RewardConfig.speed"),
        (lambda: ObservationConfig(ray_distances=(flag,)), "ObservationConfig.ray_distances"),
        (lambda: _io._scenario(dt=flag), "Scenario.dt"),
    ):
        with pytest.raises(ValueError, match=field):
            build()


def test_a_scene_at_another_time_step_is_refused_at_reset():
    import riskflow_env
    from riskflow_env.scenarios import shipped_bank

    scene = shipped_bank("eval")[0]
    env = riskflow_env.parallel_env(config=EnvConfig(dynamics=DynamicsConfig(dt=0.2)))
    with pytest.raises(ValueError, match=r"logged at dt = 0.1 s but the env steps dt = 0.2 s"):
        env.reset(options={"scenario": scene})


@pytest.mark.parametrize(
    ("action", "message"),
    [
        (np.array([np.nan, 0.0]), r"actions must be finite; got NaN or inf for \['ego'\]"),
        (np.zeros(3), r"actions\['ego'\] must have shape \(2,\)"),
        ("ab", r"actions\['ego'\] must hold real numbers"),
        (np.array([50.0, 0.0]), r"actions out of bounds for \['ego'\]"),
    ],
)
def test_the_aec_view_checks_each_action_as_it_is_given(action, message):
    import riskflow_env

    aec = riskflow_env.env(max_cycles=5, config=EnvConfig(clip_actions=False))
    aec.reset(seed=0)
    with pytest.raises(ValueError, match=message):
        aec.step(action)
    aec.step(np.zeros(2))  # the refused action was not taken: the ego steps again
    assert aec.agent_selection != "ego"
    with pytest.raises(AssertionError, match="reset"):  # PettingZoo's order check
        riskflow_env.env().step(np.zeros(2))


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"num_neighbors": 2.5}, "num_neighbors"),
        ({"num_neighbors": True}, "num_neighbors"),
        ({"ray_directions": 1.5}, "ray_directions"),
        ({"ray_distances": (1e39,)}, "ray_distances"),
        ({"ray_distances": (float("nan"),)}, "ray_distances"),
        ({"ray_distances": (True,)}, "ray_distances"),
    ],
)
def test_observation_config_values(kwargs, field):
    with pytest.raises(ValueError, match=f"ObservationConfig.{field}"):
        ObservationConfig(**kwargs)


@pytest.mark.parametrize("name", ["dt", "speed_max", "accel_max"])
def test_dynamics_config_huge_values(name):
    with pytest.raises(ValueError, match=f"DynamicsConfig.{name}"):
        DynamicsConfig(**{name: 1e300})


def test_ray_distances_list_is_accepted_as_tuple():
    assert ObservationConfig(ray_distances=[2.0, 5.0]).ray_distances == (2.0, 5.0)


def _bad_states(kind):
    scenario = _io._scenario()
    states = scenario.states.copy()
    if kind == "negative_speed":
        states[0, 5, 2] = -1.0
    elif kind == "huge":
        states[0, 5, 0] = 1e300
    return states


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"length": np.array([np.nan, 5.0, 12.0])}, "Scenario.length"),
        ({"width": np.array([1.9, np.nan, 2.5])}, "Scenario.width"),
        ({"length": np.array([1e300, 5.0, 12.0])}, "Scenario.length"),
        ({"dt": -1.0}, "Scenario.dt"),
        ({"dt": 0.0}, "Scenario.dt"),
        ({"dt": float("nan")}, "Scenario.dt"),
        ({"states": "negative_speed"}, "speed"),
        ({"states": "huge"}, "position"),
        ({"ego_index": True}, "Scenario.ego_index"),
        ({"valid": "ints"}, "Scenario.valid must be a bool array, got dtype int64"),
    ],
)
def test_scenario_invalid_values(changes, message):
    if changes.get("valid") == "ints":  # 0/1 ints would index the states, not mask them
        changes = {"valid": _io._scenario().valid.astype(np.int64)}
    if changes.get("states") in ("negative_speed", "huge"):
        changes = {"states": _bad_states(changes["states"])}
    with pytest.raises(ValueError, match=message):
        _io._scenario(**changes)


@pytest.mark.parametrize("ref", ["/etc/passwd", "../maps/x.npz", "maps/../../x.npz"])
def test_map_ref_must_stay_in_the_folder(tmp_path, ref):
    bank = tmp_path / "bank"
    bank.mkdir()
    save_scenario(_io._scenario(), bank / "scene.npz", map_dir=bank / "maps")
    path = bank / "scene.npz"
    _io._rewrite(path, map_ref=np.array(ref))
    with pytest.raises(ScenarioFormatError, match="map_ref"):
        load_scenario(path)


@pytest.mark.parametrize(
    "action",
    [
        np.array([1 + 2j, 0.0]),
        (1j, 0.0),
        "ab",
        {"a": 1},
        np.array([np.nan, 0.0]),
        0.5,
        1,
    ],
)
def test_bad_actions_name_the_agent(action):
    env = _env.make_env()
    env.reset(seed=0)
    actions = {agent: np.zeros(2) for agent in env.agents}
    agent = env.agents[-1]
    actions[agent] = action
    with pytest.raises(ValueError, match=agent):
        env.step(actions)


@pytest.mark.parametrize(
    "action",
    [
        np.array([True, False]),
        [True, False],
        (True, 0.5),
        (np.bool_(False), 0.0),
        [0.1, np.True_],
    ],
)
def test_bool_actions_are_refused_naming_the_agent(action):
    """A bool action among float ones was taken as 1.0/0.0 on the vectorised path (and a
    bool in a tuple on both paths); both paths refuse it alike."""
    env = _env.make_env()
    env.reset(seed=0)
    actions = {agent: np.zeros(2) for agent in env.agents}
    agent = env.agents[-1]
    actions[agent] = action
    message = rf"actions\['{agent}'\] must hold real numbers, got (dtype bool|a bool)"
    with pytest.raises(ValueError, match=message):
        env.step(actions)
    with pytest.raises(ValueError, match=message):
        env.action_input.check(agent, action)
    env.step({agent: [0.0, np.float32(0.0)] for agent in env.agents})  # numbers still go


def test_torch_actions_take_the_vectorised_path_and_bool_tensors_are_refused(monkeypatch):
    torch = pytest.importorskip("torch")
    env = _env.make_env()
    env.reset(seed=0)
    checked = []
    check = env.action_input.check
    monkeypatch.setattr(
        env.action_input, "check", lambda *a, **k: checked.append(a) or check(*a, **k)
    )
    env.step({agent: torch.zeros(2) for agent in env.agents})
    assert not checked  # float tensors: no agent-by-agent check
    actions = {agent: torch.zeros(2) for agent in env.agents}
    actions[env.agents[0]] = torch.tensor([True, False])
    with pytest.raises(ValueError, match="must hold real numbers, got dtype bool"):
        env.step(actions)


def test_plain_number_ignores_numpy_print_options():
    from riskflow_env.config import RewardConfig

    with np.printoptions(legacy="1.13"):
        assert RewardConfig(speed=np.float32(0.1234567)).speed == 0.1234567


def test_tensor_with_grad_names_the_agent():
    torch = pytest.importorskip("torch")
    env = _env.make_env()
    env.reset(seed=0)
    actions = {agent: np.zeros(2) for agent in env.agents}
    agent = env.agents[0]
    actions[agent] = torch.zeros(2, requires_grad=True)
    with pytest.raises(ValueError, match=agent):
        env.step(actions)


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"seed": -1}, ValueError, r"reset\(seed=...\) must be None or an int >= 0, got -1"),
        ({"seed": 1.5}, TypeError, r"reset\(seed=...\) must be None or an int >= 0, got float"),
        ({"seed": True}, TypeError, r"reset\(seed=...\) must be None or an int >= 0, got bool"),
        ({"seed": "0"}, TypeError, r"reset\(seed=...\) must be None or an int >= 0, got str"),
        ({"options": "str"}, TypeError, r"reset\(options=...\) must be None or a dict"),
        ({"options": [("scenario", 1)]}, TypeError, r"reset\(options=...\) must be None or a dict"),
    ],
)
@pytest.mark.parametrize("kind", ["parallel", "ego"])
def test_bad_reset_arguments_name_the_argument(kind, kwargs, error, message):
    """Issue 19: `reset(options="str")` and `reset(seed=-1)` failed deep inside (dict
    update, numpy's SeedSequence). gymnasium's seeding refuses negative seeds too."""
    env = _env.make_env() if kind == "parallel" else EgoEnv(env=_env.make_env())
    with pytest.raises(error, match=message):
        env.reset(**kwargs)


def test_numpy_integer_seed_is_the_same_seed():
    first = _env.make_env().reset(seed=np.int64(3))[0]
    second = _env.make_env().reset(seed=3)[0]
    assert first.keys() == second.keys()
    assert all(np.array_equal(first[agent], second[agent]) for agent in first)


def test_an_action_error_names_a_few_agents_and_counts_the_rest():
    import riskflow_env

    env = riskflow_env.parallel_env(config=EnvConfig(clip_actions=False))
    env.reset(seed=0)
    count = len(env.agents)
    with pytest.raises(ValueError, match=rf"\['ego', .*'agent_4'\] and {count - 5} more$"):
        env.step({agent: np.array([np.nan, 0.0]) for agent in env.agents})
    with pytest.raises(ValueError, match=rf"bounds for \[.*\] and {count - 5} more: accel"):
        env.step({agent: np.array([50.0, 0.0]) for agent in env.agents})
