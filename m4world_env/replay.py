"""Log-replay scenarios: an imported real-driving clip (``m4world import nuscenes``) as a scenario.

The logged agents become scripted objects following their logged tracks (``waypoints``, or
``static`` when they do not move); the ego starts where and as fast as it was logged and is then
driven by the policy. Poses are expressed in the ego's logged start frame (the ego at the origin,
heading +x). The road is a ``route`` road (``docs/data.md``):

* ``map_expansion``: where the import found the lanes the logged ego drove along
  (``route_centerline`` in the clip's meta), one lane on their joined centerline, the map
  expansion's drivable area and dividers drawn around it, on-road meaning inside that area;
* ``ego_path``: otherwise, three lanes following the logged ego path (extended straight at both
  ends), the ego in the middle one.

Progress is scored along the logged ego path (``road.reference_path``); the road's speed limit is the ego's
mean logged speed, which the policies' target speeds follow.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import yaml

from m4world_env.scenario import scenario_from_dict
from m4world_env.traffic.polyline import Polyline
from world_model.data import read_clip
from world_model.data.clips import Clip
from world_model.scene import MapGeometry

REPLAY_LANES = 3  # ego_path roads: the ego's lane and one on each side
REPLAY_EGO_LANE = 1
REPLAY_LANE_WIDTH = 4.0
REPLAY_BEHIND_M = 30.0  # ego_path roads start this far behind the ego's logged start
REPLAY_AHEAD_M = 100.0  # and end this far past its logged end (a policy may drive farther than the log)
LANE_VERTEX_SPACING_M = 0.5  # logged path vertices closer than this to the previous one are dropped
# The road's speed limit is the ego's mean logged speed (at least this): the policies' target speeds.
MIN_REPLAY_SPEED_LIMIT = 2.0
REPLAY_POLICY_FREQUENCY = 5
STATIC_MOTION_M = 0.5  # an agent that moves less than this over the clip is kept as a static object
COORDINATE_DECIMALS = 3
MIN_ROUTE_STEP_M = 0.1  # the route of an ego that never moved: this long, along its heading


def _thinned(points: np.ndarray, spacing: float) -> np.ndarray:
    """``points`` without those closer than ``spacing`` to the previous kept one (the last is kept)."""
    keep = [0]
    for i in range(1, len(points)):
        if np.hypot(*(points[i] - points[keep[-1]])) >= spacing:
            keep.append(i)
    if keep[-1] != len(points) - 1 and np.hypot(*(points[-1] - points[keep[-1]])) > 1e-3:
        keep.append(len(points) - 1)
    return points[keep]


def path_lanes(path: np.ndarray, start_yaw: float, end_yaw: float) -> list[Polyline]:
    """``REPLAY_LANES`` lanes (leftmost first) following ``path``, extended ``REPLAY_BEHIND_M`` back
    along ``start_yaw`` and ``REPLAY_AHEAD_M`` on along ``end_yaw``; the middle one is the path."""
    back = path[0] - REPLAY_BEHIND_M * np.array([math.cos(start_yaw), math.sin(start_yaw)])
    ahead = path[-1] + REPLAY_AHEAD_M * np.array([math.cos(end_yaw), math.sin(end_yaw)])
    middle = Polyline.from_points(np.concatenate([[back], _thinned(path, LANE_VERTEX_SPACING_M), [ahead]]))
    offsets = [(REPLAY_EGO_LANE - k) * REPLAY_LANE_WIDTH for k in range(REPLAY_LANES)]
    return [middle.offset(d) if d else middle for d in offsets]


def _rounded(points: np.ndarray) -> list[list[float]]:
    return np.round(np.asarray(points, dtype=np.float64), COORDINATE_DECIMALS).tolist()


def _route_map(m: MapGeometry, to_local: Callable[[np.ndarray], np.ndarray]) -> dict:
    """The scenario's ``road.map`` from the clip's map geometry, in the replay frame."""
    return {
        "drivable_area": [_rounded(to_local(p)) for p in m.drivable_area],
        "lane_lines": [
            {"kind": ln.kind, "points": _rounded(to_local(ln.points))} for ln in m.lane_lines if ln.kind != "none"
        ],
        "road_edges": [_rounded(to_local(e)) for e in m.road_edges],
    }


def replay_dict(clip: Clip) -> dict:
    """The scenario (as a YAML-ready dict) replaying ``clip``'s logged agents around a policy ego."""
    frames = clip.frames
    first = frames[0].ego
    c, s = math.cos(first.yaw), math.sin(first.yaw)

    def to_local(points: np.ndarray) -> np.ndarray:
        d = np.asarray(points, dtype=np.float64).reshape(-1, 2) - (first.x, first.y)
        return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)

    tracks: dict[str, list[tuple[float, float, float, float]]] = {}
    meta: dict[str, tuple[str, tuple[float, float, float], str]] = {}
    for fr in frames:
        for o in fr.objects:
            ((x, y),) = to_local(np.array(o.box.center[:2]))
            tracks.setdefault(o.track_id, []).append(
                (round(fr.time, 3), float(x), float(y), math.remainder(o.box.yaw - first.yaw, 2 * math.pi))
            )
            meta[o.track_id] = (o.category, o.box.size, o.description)
    objects = []
    for tid, points in tracks.items():
        category, size, description = meta[tid]
        xy = np.array([(p[1], p[2]) for p in points])
        moved = float(np.linalg.norm(xy - xy[0], axis=1).max())
        if moved < STATIC_MOTION_M or len(points) < 2:
            t, x, y, yaw = points[0]
            track = {"kind": "static", "x": round(x, 3), "y": round(y, 3), "yaw": round(yaw, 4)}
        else:
            track = {
                "kind": "waypoints",
                "points": [
                    {"t": t, "x": round(x, 3), "y": round(y, 3), "yaw": round(yaw, 4)} for t, x, y, yaw in points
                ],
            }
        objects.append(
            {
                "id": tid,
                "category": category,
                "description": f"a logged {description}" if description else "",
                "size": [round(v, 3) for v in size],
                "track": track,
            }
        )
    duration = max(frames[-1].time, 1.0 / REPLAY_POLICY_FREQUENCY)
    logged = to_local(np.array([(f.ego.x, f.ego.y) for f in frames]))
    logged_distance = float(np.linalg.norm(np.diff(logged, axis=0), axis=1).sum())
    speed_limit = max(logged_distance / duration, MIN_REPLAY_SPEED_LIMIT)
    road, ego_lane = _road(clip, logged, to_local)
    start_s, _ = Polyline.from_points(road["lanes"][ego_lane]).project(np.zeros((1, 2)))
    return {
        "name": f"replay_{clip.name}",
        "road": {**road, "speed_limit": round(speed_limit, 3)},
        "duration": round(math.ceil(duration * REPLAY_POLICY_FREQUENCY) / REPLAY_POLICY_FREQUENCY, 3),
        "policy_frequency": REPLAY_POLICY_FREQUENCY,
        "sensor_frequency": 2 * REPLAY_POLICY_FREQUENCY,
        "prompt": frames[0].prompt.text,
        "ego": {
            "lane": ego_lane,
            "longitudinal": round(max(float(start_s[0]), 0.0), 3),
            "speed": round(first.speed, 3),
        },
        "traffic": {"count": 0},
        "objects": objects,
    }


def _road(clip: Clip, logged: np.ndarray, to_local: Callable[[np.ndarray], np.ndarray]) -> tuple[dict, int]:
    """The replay's ``route`` road (without its speed limit), in the replay frame, and the ego's lane."""
    try:
        route = Polyline.from_points(_thinned(logged, LANE_VERTEX_SPACING_M)).points
    except ValueError:  # the logged ego stood still: a route of no length, along its heading
        route = np.array([[0.0, 0.0], [MIN_ROUTE_STEP_M, 0.0]])
    if "route_centerline" in clip.meta:
        centerline = to_local(np.asarray(clip.meta["route_centerline"], dtype=np.float64))
        road = {
            "type": "route",
            "source": "map_expansion",
            "lanes": [_rounded(centerline)],
            "reference_path": _rounded(route),
            "lane_width": round(float(clip.meta["route_lane_width"]), 3),
            "map": _route_map(clip.frames[0].map, to_local),
        }
        return road, 0
    end_yaw = clip.frames[-1].ego.yaw - clip.frames[0].ego.yaw
    lanes = path_lanes(logged, 0.0, end_yaw)
    road = {
        "type": "route",
        "source": "ego_path",
        "lanes": [_rounded(lane.points) for lane in lanes],
        "reference_path": _rounded(route),
        "lane_width": REPLAY_LANE_WIDTH,
    }
    return road, REPLAY_EGO_LANE


def write_replay_scenarios(data: str | Path, names: list[str], out: str | Path) -> list[Path]:
    """Write ``<out>/replay_<clip>.yaml`` for each named clip of dataset ``data``; each file is
    validated as a scenario before it is written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in names:
        d = replay_dict(read_clip(data, name))
        path = out / f"{d['name']}.yaml"
        scenario_from_dict(d, source=str(path))
        path.write_text(yaml.safe_dump(d, sort_keys=False))
        paths.append(path)
    return paths
