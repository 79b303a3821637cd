"""Map raster size and build time of ScenarioNet scenes: whole recording area vs cropped.

A synthetic nuScenes-style description (ScenarioNet's converter form: lane polylines and
polygons every ``segment`` metres, the drivable area as ``boundary_<k>`` rings) covers
a square city grid of ``area`` metres with two-lane streets every ``block`` metres;
the logged vehicles drive within ``vehicle_extent`` metres of the centre. Each row loads
the scene with :func:`~riskflow_env.scenarios.scenarionet.scenario_from_description`
(map building included) and prints the raster shape, its size (drivable mask + signed
distance field) and the median build time; ``ratio`` compares with the uncropped row.
Add ``--files`` to measure ScenarioNet pickles as well.

    python benchmarks/scenarionet_map_size.py [--area 2500] [--repeats 3]
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

import numpy as np
import shapely

from policies.dataclass_cli import check_at_least, check_between, parse_dataclass
from riskflow_env.cli_errors import run_script
from riskflow_env.scenarios.safe_pickle import load_data_pickle
from riskflow_env.scenarios.scenarionet import scenario_from_description


@dataclass(frozen=True)
class Options:
    """Benchmark options."""

    area: float = 2500.0
    """side of the synthetic recording area [m]"""
    block: float = 100.0
    """street spacing of the synthetic grid [m]"""
    segment: float = 50.0
    """length of one lane feature [m]"""
    vehicle_extent: float = 300.0
    """side of the square the logged vehicles drive in [m]"""
    vehicles: int = 40
    """logged vehicles of the synthetic scene"""
    resolution: float = 0.5
    """raster resolution [m/px]"""
    repeats: int = 3
    """timed builds per row (the median is reported)"""
    files: tuple[str, ...] = ()
    """ScenarioNet pickles to measure too"""

    def __post_init__(self) -> None:
        check_at_least(self, {"vehicles": 1, "repeats": 1})
        positive = ("area", "block", "segment", "vehicle_extent", "resolution")
        check_between(self, dict.fromkeys(positive, (0.0, 1e5)))


def synthetic_city(options: Options, seed: int = 0) -> dict:
    """nuScenes-style description of a grid city (see the module docstring)."""
    half, lane = options.area / 2, 3.5
    streets = np.arange(-half, half + 1e-6, options.block)
    features, roads = {}, []
    cuts = np.arange(-half, half, options.segment)
    for axis in (0, 1):
        for c in streets:
            roads.append(
                shapely.box(-half, c - lane, half, c + lane)
                if axis == 0
                else shapely.box(c - lane, -half, c + lane, half)
            )
            for direction, offset in ((1, -lane / 2), (-1, lane / 2)):
                for s in cuts:
                    along = np.linspace(s, s + options.segment, 11)[::direction]
                    across = np.full_like(along, c + offset)
                    line = np.stack([along, across] if axis == 0 else [across, along], 1)
                    outline = shapely.LineString(line).buffer(lane / 2, cap_style="flat")
                    key = f"lane-{axis}-{c:.0f}-{direction}-{s:.0f}"
                    features[key] = {
                        "type": "LANE_SURFACE_STREET",
                        "polyline": np.concatenate([line, np.zeros((len(line), 1))], 1),
                        "polygon": np.asarray(outline.exterior.coords),
                    }
    area = shapely.union_all(roads)
    rings = [area.exterior, *area.interiors]
    for k, ring in enumerate(rings):
        features[f"boundary_{k}"] = {
            "type": "ROAD_LINE_SOLID_SINGLE_WHITE",
            "polyline": np.asarray(ring.coords),
        }
    rng = np.random.default_rng(seed)
    steps, tracks = 201, {}
    for i in range(options.vehicles):
        street = rng.choice(streets[np.abs(streets) <= options.vehicle_extent / 2])
        start = rng.uniform(-options.vehicle_extent / 2, options.vehicle_extent / 2 - 100)
        along = start + np.arange(steps) * 0.1 * rng.uniform(0, 10)
        across = np.full(steps, street - lane / 2)
        xy = np.stack([along, across] if i % 2 == 0 else [across, along], 1)
        velocity = np.gradient(xy, 0.1, axis=0)
        tracks["ego" if i == 0 else f"car{i}"] = {
            "type": "VEHICLE",
            "state": {
                "position": np.concatenate([xy, np.zeros((steps, 1))], 1),
                "heading": np.full(steps, 0.0 if i % 2 == 0 else np.pi / 2),
                "velocity": velocity,
                "valid": np.ones(steps),
                "length": np.full((steps, 1), 4.5),
                "width": np.full((steps, 1), 1.9),
            },
        }
    metadata = {"sdc_id": "ego", "sample_rate": 0.1, "ts": np.arange(steps) * 0.1}
    metadata["scenario_id"] = "synthetic-city"
    return {"tracks": tracks, "map_features": features, "metadata": metadata}


def measure(description: dict, options: Options, crop: bool) -> tuple:
    """(raster shape, raster MB, median build seconds) of one description."""
    times = []
    for _ in range(options.repeats):
        start = time.perf_counter()
        scenario = scenario_from_description(description, options.resolution, crop=crop)
        times.append(time.perf_counter() - start)
    size = (scenario.map.drivable.nbytes + scenario.map.sdf.nbytes) / 2**20
    return scenario.map.shape, size, statistics.median(times)


PROG = "scenarionet_map_size.py"  # the name in usage and error lines


def main(argv: list[str] | None = None) -> None:
    options = parse_dataclass(
        Options, argv, prog=PROG, description=__doc__.split("\n")[0], debug=True
    )
    scenes = [(f"synthetic {options.area:g} m city", synthetic_city(options))]
    scenes += [(name, load_data_pickle(name)) for name in options.files]
    print(
        f"{'scene':<40} {'crop':<5} {'raster [px]':>14} {'size [MB]':>10} {'build [s]':>10} ratio"
    )
    for name, description in scenes:
        whole = None
        for crop in (False, True):
            shape, size, seconds = measure(description, options, crop)
            whole = whole or (size, seconds)
            ratio = f"{whole[0] / size:.1f}x smaller, {whole[1] / seconds:.1f}x faster"
            print(
                f"{name[-40:]:<40} {crop!s:<5} {f'{shape[0]} x {shape[1]}':>14} "
                f"{size:>10.1f} {seconds:>10.2f} {ratio if crop else ''}"
            )


if __name__ == "__main__":
    run_script(PROG, main)
