"""Maps of the highway-env families: they build, and highway-env's own traffic lies on them."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

from riskflow_env.maps import FAMILIES, DrivableMap, RoadFamily, from_highway_env, road_family
from riskflow_env.maps.highway import ENV_IDS

SEEDS = (0, 1, 2, 3)
CORNER_TOLERANCE = 0.05  # [m] allowed SDF at vehicle corners (raster discretisation)
# highway-v0 spawns traffic over x in ~[170, 1250] m: its map needs longer lanes
MAX_LENGTH = {"highway": 1600.0}


@pytest.mark.parametrize("family", FAMILIES)
def test_family_builds(family: str) -> None:
    road = from_highway_env(family)
    assert isinstance(road, DrivableMap) and road.name == family
    assert road.resolution == 0.5 and road.drivable.any() and not road.drivable.all()
    assert road.lanes and all(lane.length <= 600.0 + 1e-9 for lane in road.lanes)
    ids = {lane.lane_id for lane in road.lanes}
    assert all(succ in ids for lane in road.lanes for succ in lane.successors)
    assert all(lane.speed_limit is not None and lane.width > 0 for lane in road.lanes)
    # every lane's centreline is on the road
    for lane in road.lanes:
        s = np.linspace(0.0, lane.length, 50)
        assert road.is_drivable(lane.position(s)[0]).all(), lane.lane_id
    assert from_highway_env(family) is road  # cached


def _footprints(env) -> tuple[np.ndarray, np.ndarray]:
    """Centres (V, 2) and corners (V, 4, 2) [m] of all vehicles of a highway-env env."""
    centres, corners = [], []
    for vehicle in env.road.vehicles:
        centre = np.asarray(vehicle.position, dtype=np.float64)
        forward = np.array([np.cos(vehicle.heading), np.sin(vehicle.heading)])
        left = np.array([-forward[1], forward[0]])
        half_l, half_w = vehicle.LENGTH / 2, vehicle.WIDTH / 2
        signs = [(1, 1), (1, -1), (-1, -1), (-1, 1)]
        centres.append(centre)
        corners.append([centre + a * half_l * forward + b * half_w * left for a, b in signs])
    return np.array(centres), np.array(corners)


@pytest.mark.parametrize("family", FAMILIES)
def test_highway_env_vehicles_are_on_the_map(family: str) -> None:
    road = from_highway_env(family, max_length=MAX_LENGTH.get(family, 600.0))
    env = gymnasium.make(ENV_IDS[family]).unwrapped
    for seed in SEEDS:
        env.reset(seed=seed)
        centres, corners = _footprints(env)
        assert (road.sdf_at(centres) <= 0).all(), (seed, road.sdf_at(centres).max())
        corner_sdf = road.sdf_at(corners)
        assert (corner_sdf <= CORNER_TOLERANCE).all(), (seed, corner_sdf.max())
        # the lane a vehicle drives on agrees with highway-env's own lane coordinates
        for vehicle in env.road.vehicles:
            start, end, index = vehicle.lane_index
            hw_lane = env.road.network.get_lane(vehicle.lane_index)
            s_hw, lateral_hw = hw_lane.local_coordinates(vehicle.position)
            if 0.0 <= s_hw <= road.lane_by_id(f"{start}->{end}#{index}").length:
                s, lateral = road.lane_by_id(f"{start}->{end}#{index}").project(vehicle.position)
                assert s == pytest.approx(s_hw, abs=0.05) and lateral == pytest.approx(
                    lateral_hw, abs=0.05
                )
    env.close()


def test_entry_lanes_get_an_apron() -> None:
    """u-turn's ego starts at s = 0 of an entry lane on the map's edge, its rear 2.5 m
    before the lane: on the road with the apron, and without it too (the road enters the
    map there, so the builder opens it through the margin), the raster 5 m shorter."""
    bare = from_highway_env("u-turn", entry_apron=0.0)
    env = gymnasium.make(ENV_IDS["u-turn"]).unwrapped
    env.reset(seed=0)
    _, corners = _footprints(env)
    env.close()
    assert bare.sdf_at(corners).max() < -0.5
    assert from_highway_env("u-turn").sdf_at(corners).max() < -0.5
    assert bare.bounds[0] == from_highway_env("u-turn").bounds[0] + 5.0


@pytest.mark.parametrize("family", FAMILIES)
def test_a_car_driving_any_lane_stays_on_the_road(family: str) -> None:
    """5 m x 2 m footprints along every lane centreline, through the junctions."""
    road = from_highway_env(family)
    for lane in road.lanes:
        # a dead-end lane ends the road: stop when the nose reaches its end
        s = np.arange(0.0, lane.length - (0.0 if lane.successors else 2.5), 0.25)
        xy, heading = lane.position(s)
        forward = np.stack([np.cos(heading), np.sin(heading)], axis=-1)
        left = np.stack([-forward[:, 1], forward[:, 0]], axis=-1)
        corners = np.stack([xy + a * 2.5 * forward + b * left for a in (-1, 1) for b in (-1, 1)])
        # half a pixel: a roundabout entry ends beside the ring in a wedge
        assert road.sdf_at(corners).max() <= road.resolution / 2, lane.lane_id


def test_successors_continue_their_lane() -> None:
    """highway-env's next-lane rule also names lane changes and U-turns; those are dropped."""
    roundabout = from_highway_env("roundabout")
    assert roundabout.lane_by_id("se->ex#0").successors == ("ex->ee#0",)  # not the exit
    intersection = from_highway_env("intersection")
    assert intersection.lane_by_id("il0->o0#0").successors == ()  # not o0->ir0 (U-turn)
    racetrack = from_highway_env("racetrack")
    assert all(len(lane.successors) == 1 for lane in racetrack.lanes)  # closed circuit


def test_long_lanes_are_cut() -> None:
    road = from_highway_env("highway")
    assert [lane.length for lane in road.lanes] == pytest.approx([600.0] * 4)
    assert all(lane.successors == () for lane in road.lanes)
    # 5 m entry apron before x = 0, 5 m margin on every side
    assert road.bounds[0] == pytest.approx(-10.0) and road.bounds[2] == pytest.approx(605.0)
    # the cut road leaves the map at both ends: it goes on beyond the raster
    assert road.is_drivable(np.array([[700.0, 6.0], [-50.0, 6.0]])).all()


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"family": "parking"}, "valid families: highway, merge, roundabout"),
        ({"family": "merge", "resolution": 0}, "resolution"),
        ({"family": "merge", "max_length": -1.0}, "max_length"),
        ({"family": "merge", "seed": 1.5}, "seed"),
        ({"family": "merge", "entry_apron": float("nan")}, "entry_apron"),
    ],
)
def test_bad_arguments(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        from_highway_env(**kwargs)


def test_road_family_enum_names_every_family() -> None:
    assert FAMILIES == tuple(family.value for family in RoadFamily)
    assert road_family(RoadFamily.U_TURN) == "u-turn" == road_family("u-turn")
    assert from_highway_env(RoadFamily.MERGE) is from_highway_env("merge")  # one cached map
    with pytest.raises(ValueError, match="unknown family 'parking'; valid families: highway"):
        road_family("parking")
