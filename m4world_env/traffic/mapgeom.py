"""Sample a highway-env road network into :class:`world_model.MapGeometry` (our frame).

Each lane gives: its two side lines with kinds from highway-env's ``LineType``
(CONTINUOUS / CONTINUOUS_LINE -> solid, STRIPED -> dashed, NONE -> none), a drivable-area strip
polygon, and road edges on the sides that are the outside of the carriageway.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from highway_env.road.lane import AbstractLane, LineType, StraightLane

from m4world_env.traffic.roads import RoadLayout
from world_model.scene import LaneLine, MapGeometry

LINE_KINDS = {
    LineType.NONE: "none",
    LineType.STRIPED: "dashed",
    LineType.CONTINUOUS: "solid",
    LineType.CONTINUOUS_LINE: "solid",
}


@dataclass(frozen=True)
class MapSamplingConfig:
    curve_step_m: float = 2.0  # spacing of samples along curved lanes
    include_invisible_lines: bool = True  # keep kind "none" boundaries (useful for lane ids)


def _is_straight(lane: AbstractLane) -> bool:
    return type(lane) is StraightLane


def _sample_s(lane: AbstractLane, cfg: MapSamplingConfig) -> np.ndarray:
    if _is_straight(lane):
        return np.array([0.0, lane.length])
    n = max(2, math.ceil(lane.length / cfg.curve_step_m) + 1)
    return np.linspace(0.0, lane.length, n)


def _to_ours(points_hw: np.ndarray) -> np.ndarray:
    return np.stack([points_hw[:, 0], -points_hw[:, 1]], axis=-1)


def extract_map(layout: RoadLayout, cfg: MapSamplingConfig = MapSamplingConfig()) -> MapGeometry:
    """Lane lines, road edges and per-lane drivable strips of ``layout``'s network, our frame."""
    lines: list[LaneLine] = []
    edges: list[np.ndarray] = []
    areas: list[np.ndarray] = []
    graph = layout.network.graph
    for frm, tos in graph.items():
        for to, lanes in tos.items():
            for k, lane in enumerate(lanes):
                s = _sample_s(lane, cfg)
                half = np.array([lane.width_at(x) / 2 for x in s])
                left = _to_ours(np.array([lane.position(x, -h) for x, h in zip(s, half, strict=True)]))
                right = _to_ours(np.array([lane.position(x, h) for x, h in zip(s, half, strict=True)]))
                areas.append(np.concatenate([left, right[::-1]], axis=0))
                for side, pts in ((0, left), (1, right)):
                    kind = LINE_KINDS[lane.line_types[side]]
                    if kind != "none" or cfg.include_invisible_lines:
                        lines.append(LaneLine(points=pts, kind=kind))
                    outermost = k == 0 if side == 0 else k == len(lanes) - 1
                    if outermost and ((frm, to, k), side) not in layout.inner_sides:
                        edges.append(pts)
    return MapGeometry(
        lane_lines=tuple(lines),
        road_edges=tuple(edges),
        drivable_area=tuple(areas),
        lane_width=layout.lane_width,
    )
