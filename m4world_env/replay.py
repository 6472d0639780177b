"""Log-replay scenarios: an imported real-driving clip (``m4world import nuscenes``) as a scenario.

The logged agents become scripted objects following their logged tracks (``waypoints``, or
``static`` when they do not move); the ego starts where and as fast as it was logged and is then
driven by the policy. The road is a straight highway laid along the ego's logged start heading,
the ego in its middle lane: logged poses are expressed relative to the ego's start pose and placed
on that road. Roads that curve or junctions are not reproduced (``docs/data.md``). The road's
speed limit is the ego's mean logged speed, so the progress score compares the policy's distance
with the logged ego's.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from m4world_env.scenario import scenario_from_dict
from world_model.data import read_clip
from world_model.data.clips import Clip

REPLAY_LANES = 3
REPLAY_EGO_LANE = 1
REPLAY_LANE_WIDTH = 4.0
REPLAY_EGO_LONGITUDINAL = 30.0  # metres of road behind the ego's start
REPLAY_ROAD_LENGTH = 1000.0
# The road's speed limit is the ego's mean logged speed (at least this), so the environment's
# progress score (distance over speed limit x duration) reads 1 when the policy covers the logged
# distance: progress is measured against the log's, as NAVSIM measures it against a reference.
MIN_REPLAY_SPEED_LIMIT = 2.0
REPLAY_POLICY_FREQUENCY = 5
STATIC_MOTION_M = 0.5  # an agent that moves less than this over the clip is kept as a static object


def replay_dict(clip: Clip) -> dict:
    """The scenario (as a YAML-ready dict) replaying ``clip``'s logged agents around a policy ego."""
    frames = clip.frames
    first = frames[0].ego
    c, s = math.cos(first.yaw), math.sin(first.yaw)
    lane_y = -REPLAY_EGO_LANE * REPLAY_LANE_WIDTH

    def place(x: float, y: float) -> tuple[float, float]:
        dx, dy = x - first.x, y - first.y
        return REPLAY_EGO_LONGITUDINAL + c * dx + s * dy, lane_y - s * dx + c * dy

    tracks: dict[str, list[tuple[float, float, float, float]]] = {}
    meta: dict[str, tuple[str, tuple[float, float, float], str]] = {}
    for fr in frames:
        for o in fr.objects:
            x, y = place(o.box.center[0], o.box.center[1])
            tracks.setdefault(o.track_id, []).append(
                (round(fr.time, 3), x, y, math.remainder(o.box.yaw - first.yaw, 2 * math.pi))
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
    logged = np.array([(f.ego.x, f.ego.y) for f in frames])
    logged_distance = float(np.linalg.norm(np.diff(logged, axis=0), axis=1).sum())
    speed_limit = max(logged_distance / duration, MIN_REPLAY_SPEED_LIMIT)
    return {
        "name": f"replay_{clip.name}",
        "road": {
            "type": "highway",
            "lanes": REPLAY_LANES,
            "length": REPLAY_ROAD_LENGTH,
            "speed_limit": round(speed_limit, 3),
            "lane_width": REPLAY_LANE_WIDTH,
        },
        "duration": round(math.ceil(duration * REPLAY_POLICY_FREQUENCY) / REPLAY_POLICY_FREQUENCY, 3),
        "policy_frequency": REPLAY_POLICY_FREQUENCY,
        "sensor_frequency": 2 * REPLAY_POLICY_FREQUENCY,
        "prompt": frames[0].prompt.text,
        "ego": {"lane": REPLAY_EGO_LANE, "longitudinal": REPLAY_EGO_LONGITUDINAL, "speed": round(first.speed, 3)},
        "traffic": {"count": 0},
        "objects": objects,
    }


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
