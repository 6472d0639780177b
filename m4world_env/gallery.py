"""Gallery of procedural renderings: one PNG mosaic (all views + LiDAR + BEV) per case.

``m4world gallery --out docs/images`` renders each (scenario, weather, time of day) case a few
seconds into an episode driven by the IDM autopilot, at a resolution large enough to read.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from m4world_env.policies import IDMAutopilot
from m4world_env.scenario import load_scenario
from m4world_env.traffic import TrafficBridge
from world_model.sensors import default_rig
from world_model.sim import ProceduralSimulator, mosaic

# (scenario, weather, time of day): every road type, weather and time of day at least once.
DEFAULT_CASES: tuple[tuple[str, str, str], ...] = (
    ("highway_sunny_day", "sunny", "day"),
    ("highway_dense_rain_dusk", "rain", "dusk"),
    ("merge_cut_in", "cloudy", "day"),
    ("roundabout_fog", "fog", "day"),
    ("intersection_pedestrian_night", "sunny", "night"),
    ("stopped_vehicle_snow", "snow", "day"),
    ("tree_truck_highway", "sunny", "day"),
    ("two_way_overtake_dusk", "cloudy", "dusk"),
    ("highway_sunny_day", "rain", "night"),
)


def render_case(
    scenario: str, weather: str, time_of_day: str, seconds: float, height: int, width: int, seed: int = 0
) -> np.ndarray:
    """Drive ``seconds`` into the scenario with the autopilot and return the mosaic of that frame."""
    sc = load_scenario(scenario).model_copy(update={"weather": weather, "time_of_day": time_of_day})
    bridge = TrafficBridge(sc, action_type="discrete_meta", rig=default_rig(width=width, height=height))
    frame = bridge.reset(seed=seed)
    policy = IDMAutopilot(seed=seed)
    while frame.time < seconds and not (bridge.truncated or bridge.crashed):
        frame = bridge.step(policy(bridge))[-1]
    return mosaic(ProceduralSimulator().render(frame), frame)


def make_gallery(
    out: str | Path,
    cases: Sequence[tuple[str, str, str]] = DEFAULT_CASES,
    seconds: float = 3.0,
    height: int = 128,
    width: int = 224,
) -> list[Path]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for scenario, weather, tod in cases:
        img = render_case(scenario, weather, tod, seconds, height, width)
        path = out / f"{scenario}__{weather}_{tod}.png"
        cv2.imwrite(str(path), img[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
        paths.append(path)
    return paths
