"""Small deterministic demo scenes (straight highway, ring road) for benchmarks, galleries and docs.

Scenario code builds real scenes from highway-env roads; these exist so the simulator can be
exercised and measured on its own.
"""

from __future__ import annotations

import numpy as np

from world_model.scene import (
    CATEGORIES,
    CATEGORY_SIZES,
    NAMED_COLORS,
    Box3D,
    EgoState,
    LaneLine,
    MapGeometry,
    SceneFrame,
    SceneObject,
    ScenePrompt,
)
from world_model.sensors import CameraRig, default_rig

# The demo highway's lanes: demo_frame places its vehicles in them and its shoulder objects beside them.
DEMO_LANES = 4
DEMO_LANE_WIDTH_M = 4.0


def straight_road(
    num_lanes: int = DEMO_LANES, lane_width: float = DEMO_LANE_WIDTH_M, x0: float = -300.0, x1: float = 1500.0
) -> MapGeometry:
    """Lanes along +x; lane k is centred at y = -k * lane_width (lane 0 leftmost, as highway-env's)."""
    if num_lanes < 1:
        raise ValueError(f"num_lanes must be >= 1, got {num_lanes}")
    bounds = [lane_width / 2 - k * lane_width for k in range(num_lanes + 1)]
    xs = np.array([x0, x1])
    lines = tuple(
        LaneLine(points=np.stack([xs, [y, y]], 1), kind="solid" if k in (0, num_lanes) else "dashed")
        for k, y in enumerate(bounds)
    )
    strips = tuple(
        np.array([[x0, bounds[k + 1]], [x1, bounds[k + 1]], [x1, bounds[k]], [x0, bounds[k]]]) for k in range(num_lanes)
    )
    edges = (np.stack([xs, [bounds[0]] * 2], 1), np.stack([xs, [bounds[-1]] * 2], 1))
    return MapGeometry(lane_lines=lines, road_edges=edges, drivable_area=strips, lane_width=lane_width)


def ring_road(radius: float = 30.0, num_lanes: int = 2, lane_width: float = 4.0, segments: int = 96) -> MapGeometry:
    """A roundabout-like ring centred at the origin; drivable area as one quad per arc segment."""
    ang = np.linspace(0.0, 2 * np.pi, segments + 1)
    circle = np.stack([np.cos(ang), np.sin(ang)], 1)
    radii = [radius + k * lane_width for k in range(num_lanes + 1)]
    lines = tuple(
        LaneLine(points=r * circle, kind="solid" if k in (0, num_lanes) else "dashed") for k, r in enumerate(radii)
    )
    quads = tuple(
        np.array([radii[0] * circle[i], radii[-1] * circle[i], radii[-1] * circle[i + 1], radii[0] * circle[i + 1]])
        for i in range(segments)
    )
    return MapGeometry(
        lane_lines=lines,
        road_edges=(radii[0] * circle, radii[-1] * circle),
        drivable_area=quads,
        lane_width=lane_width,
    )


def demo_frame(
    num_objects: int = 18,
    seed: int = 0,
    weather: str = "sunny",
    time_of_day: str = "day",
    rig: CameraRig | None = None,
    road: MapGeometry | None = None,
    frame_index: int = 0,
    ego_x: float = 0.0,
) -> SceneFrame:
    """A frame of the demo highway (:func:`straight_road`'s defaults) with ``num_objects`` objects of
    every category around the ego (deterministic).

    Vehicles sit in lanes ahead and behind; pedestrians, cones and barriers on the shoulders.
    Pass the same ``road`` (and ``rig``) object for every frame of a sequence so caches are shared.
    """
    rng = np.random.default_rng(seed)
    road = road if road is not None else straight_road()
    num_lanes, lane_width = DEMO_LANES, DEMO_LANE_WIDTH_M
    colors = list(NAMED_COLORS)
    shoulder = {"pedestrian", "cone", "barrier"}
    objects = []
    slots = set()
    for i in range(num_objects):
        cat = CATEGORIES[i % len(CATEGORIES)]
        size = CATEGORY_SIZES[cat]
        for _ in range(100):  # find a free slot
            if cat in shoulder:
                side = rng.choice([lane_width / 2 + 1.5, lane_width / 2 - num_lanes * lane_width - 1.5])
                y, yaw = float(side), float(rng.uniform(-np.pi, np.pi)) if cat == "pedestrian" else 0.0
            else:
                lane = int(rng.integers(0, num_lanes))
                y, yaw = -lane * lane_width, 0.0
            x = ego_x + float(rng.choice([-1, 1]) * rng.uniform(8.0, 70.0))
            slot = (round(y), round(x / 14.0))
            if slot not in slots:
                slots.add(slot)
                break
        name = colors[int(rng.integers(0, len(colors)))] if cat != "cone" else "orange"
        objects.append(
            SceneObject(
                track_id=f"{cat}_{i}",
                category=cat,
                box=Box3D((x, y, size[2] / 2), size, yaw),
                color=NAMED_COLORS[name],
                color_name=name,
                description=f"a {name} {cat.replace('_', ' ')}",
                velocity=(0.0, 0.0) if cat in shoulder else (20.0, 0.0),
            )
        )
    return SceneFrame(
        time=0.1 * frame_index,
        frame_index=frame_index,
        ego=EgoState(x=ego_x, y=-lane_width, yaw=0.0, speed=20.0),
        objects=tuple(objects),
        map=road,
        prompt=ScenePrompt("a multi-lane highway", weather, time_of_day),
        rig=rig or default_rig(),
        scenario="demo",
    )
