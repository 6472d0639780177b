"""Scripted objects and the appearance (category, colour, text) of every traffic participant.

A scripted object is a highway-env ``Obstacle`` whose pose follows a track in time, so IDM
vehicles brake for it (it is found by ``Road.neighbour_vehicles``) and collisions with it count.
Tracks are evaluated in highway-env's frame; scenario coordinates (our frame) are converted once.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from highway_env.road.lane import AbstractLane
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.objects import Obstacle

from m4world_env.scenario import CutInTrack, LaneFollowTrack, ObjectSpec, StaticTrack, WaypointsTrack
from m4world_env.traffic.sim import size_object
from world_model.geometry import world_to_highway

Pose = tuple[float, float, float]  # highway-env x, y, heading

# Nouns for generated descriptions ("a red sedan"); a list means one is drawn per vehicle.
CATEGORY_NOUNS: dict[str, tuple[str, ...]] = {
    "car": ("sedan", "hatchback", "SUV", "station wagon", "coupe"),
    "truck": ("box truck", "semi-trailer truck"),
    "bus": ("city bus", "coach"),
    "van": ("delivery van", "minivan"),
    "motorcycle": ("motorcycle",),
    "cyclist": ("cyclist on a bicycle",),
    "pedestrian": ("pedestrian",),
    "cone": ("traffic cone",),
    "barrier": ("road barrier",),
    "tree_truck": ("truck hauling a load of trees",),
    "cement_mixer": ("cement mixer truck",),
}


@dataclass
class Appearance:
    """What the sensors see of an object (the model's object tokens, §3.2)."""

    category: str
    color: tuple[int, int, int]
    color_name: str
    description: str
    size: tuple[float, float, float]
    image_path: str | None = None


def describe(category: str, color_name: str, noun: str | None = None) -> str:
    noun = noun or CATEGORY_NOUNS[category][0]
    article = "an" if color_name[:1].lower() in "aeiou" else "a"
    return f"{article} {color_name.replace('_', ' ')} {noun}"


def spec_appearance(spec: ObjectSpec) -> Appearance:
    return Appearance(
        category=spec.category,
        color=spec.rgb,
        color_name=spec.color_name,
        description=spec.description or describe(spec.category, spec.color_name),
        size=spec.box_size,
        image_path=spec.image,
    )


class LanePath:
    """A lane followed into its successors (same lane id where possible), as one curve."""

    def __init__(self, network: RoadNetwork, lane_index: tuple[str, str, int], max_lanes: int = 32) -> None:
        self.lanes: list[AbstractLane] = [network.get_lane(lane_index)]
        idx = lane_index
        for _ in range(max_lanes - 1):
            nxt = network.graph.get(idx[1], {})
            if not nxt:
                break
            to = next(iter(nxt))
            idx = (idx[1], to, min(idx[2], len(nxt[to]) - 1))
            self.lanes.append(network.get_lane(idx))

    @property
    def length(self) -> float:
        return float(sum(lane.length for lane in self.lanes))

    def check_placed(self, s: float, field: str) -> None:
        """Raise ValueError if ``s`` (the track's ``field``, metres along the path) lies past the
        road's end: the object would stand off the map."""
        if s > self.length:
            raise ValueError(
                f"{field}: {s!r} m is past the road's end; the road runs {self.length:g} m along this lane"
            )

    def locate(self, s: float) -> tuple[AbstractLane, float]:
        for lane in self.lanes[:-1]:
            if s <= lane.length:
                return lane, s
            s -= lane.length
        return self.lanes[-1], s

    def pose(self, s: float, lateral: float = 0.0) -> Pose:
        lane, s_local = self.locate(s)
        p = lane.position(s_local, lateral)
        return float(p[0]), float(p[1]), float(lane.heading_at(s_local))


def _smoothstep(u: float) -> float:
    u = min(max(u, 0.0), 1.0)
    return 0.5 - 0.5 * math.cos(math.pi * u)


def make_track(spec: ObjectSpec, network: RoadNetwork, edge: tuple[str, str]) -> Callable[[float], Pose]:
    """A function of time since reset -> highway-env pose, for static/lane_follow/waypoints/cut_in."""
    tr = spec.track
    n_lanes = len(network.graph[edge[0]][edge[1]])

    def lane_path(lane: int, s: float, field: str) -> LanePath:
        if lane >= n_lanes:
            raise ValueError(f"object {spec.id!r}: lane {lane} does not exist; edge {edge} has {n_lanes} lanes")
        path = LanePath(network, (edge[0], edge[1], lane))
        path.check_placed(s, field)
        return path

    if isinstance(tr, StaticTrack):
        if tr.lane is not None:
            path = lane_path(tr.lane, tr.longitudinal, "longitudinal")
            pose = path.pose(tr.longitudinal, -tr.lateral)  # our left = highway-env's -lateral
        else:
            pose = world_to_highway(tr.x, tr.y, tr.yaw)
        return lambda t: pose
    if isinstance(tr, LaneFollowTrack):
        path = lane_path(tr.lane, tr.start, "start")
        return lambda t: path.pose(tr.start + tr.speed * t)
    if isinstance(tr, CutInTrack):
        a, b = lane_path(tr.from_lane, tr.start, "start"), lane_path(tr.to_lane, tr.start, "start")

        def cut_in(t: float) -> Pose:
            s = tr.start + tr.speed * t
            f = _smoothstep((t - tr.time) / tr.duration)
            pa, pb = np.array(a.pose(s)[:2]), np.array(b.pose(s)[:2])
            p = (1 - f) * pa + f * pb
            # Heading: lane heading plus the angle of the lateral motion.
            lat_rate = (
                float(np.linalg.norm(pb - pa))
                * math.pi
                / (2 * tr.duration)
                * math.sin(math.pi * min(max((t - tr.time) / tr.duration, 0.0), 1.0))
            )
            side = math.copysign(1.0, tr.to_lane - tr.from_lane) if tr.to_lane != tr.from_lane else 0.0
            heading = a.pose(s)[2] + side * math.atan2(lat_rate, max(tr.speed, 1e-6))
            return float(p[0]), float(p[1]), heading

        return cut_in
    assert isinstance(tr, WaypointsTrack)
    times = np.array([w.t for w in tr.points])
    xy = np.array([[w.x, w.y] for w in tr.points])
    yaws = [w.yaw for w in tr.points]

    def waypoints(t: float) -> Pose:
        k = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2))
        u = float(np.clip((t - times[k]) / (times[k + 1] - times[k]), 0.0, 1.0))
        x, y = (1 - u) * xy[k] + u * xy[k + 1]
        if yaws[k] is not None and yaws[k + 1] is not None:
            yaw = yaws[k] + u * math.remainder(yaws[k + 1] - yaws[k], 2 * math.pi)
        else:
            d = xy[k + 1] - xy[k]
            yaw = math.atan2(d[1], d[0])
        return world_to_highway(float(x), float(y), float(yaw))

    return waypoints


class ScriptedObject(Obstacle):
    """An obstacle that moves along a track. Its speed is the track's finite-difference speed."""

    def __init__(self, road: Road, spec: ObjectSpec, track: Callable[[float], Pose], t0: float) -> None:
        x, y, h = track(t0)
        super().__init__(road, [x, y], h, 0.0)
        self.spec = spec
        self.track_id = spec.id
        self.track = track
        self.time = t0
        self.appearance = spec_appearance(spec)
        size_object(self, *self.appearance.size[:2])

    def advance(self, dt: float) -> None:
        """Move to the track's pose ``dt`` later (called by FastRoad.step)."""
        self.time += dt
        x, y, h = self.track(self.time)
        moved = math.hypot(x - self.position[0], y - self.position[1])
        self.position = np.array([x, y])
        self.heading = h
        self.speed = moved / dt if dt > 0 else 0.0
