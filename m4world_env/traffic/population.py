"""Who is on the road: seeded IDM traffic, scripted objects, and their interactive edits."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from highway_env.road.road import Road

from m4world_env.scenario import MAX_SPEED_MPS, LaneFollowTrack, ObjectSpec, Scenario, ScenarioError
from m4world_env.traffic.objects import (
    CATEGORY_NOUNS,
    Appearance,
    LanePath,
    ScriptedObject,
    describe,
    make_track,
)
from m4world_env.traffic.roads import RoadLayout
from m4world_env.traffic.sim import TrafficVehicle, lane_coordinates, size_object
from world_model.scene import CATEGORY_SIZES, NAMED_COLORS

if TYPE_CHECKING:
    from highway_env.road.lane import AbstractLane
    from highway_env.vehicle.kinematics import Vehicle

EDITABLE = ("category", "color", "description", "image", "size", "speed", "track")


class UnknownObjectError(KeyError):
    """No object with that track id."""


@dataclass(frozen=True)
class PopulationConfig:
    """Traffic spawning. Spacing follows highway-env's ``Vehicle.create_random``."""

    speed_fraction: tuple[float, float] = (0.7, 0.8)  # initial speed, fraction of the lane's limit
    base_spacing_m: float = 12.0  # highway-env: spacing = (12 + speed) * exp(-5/40 * lanes) / density
    lane_count_decay: float = 5.0 / 40.0
    rear_fraction: float = 0.3  # share of the ego road's traffic window behind the ego
    clearance_m: float = 4.0  # minimum bumper-to-bumper gap at spawn
    edge_margin_m: float = 10.0  # keep spawns this far from lane ends
    attempts: int = 40  # rejection-sampling tries per vehicle before it is dropped
    departure_margin_m: float = 20.0  # despawn IDM vehicles this far past the network's end


def is_vehicle(obj: object) -> bool:
    return isinstance(obj, TrafficVehicle)


def _traffic_appearance(s: Scenario, rng: np.random.Generator) -> Appearance:
    cats = list(s.traffic.mix)
    w = np.array([s.traffic.mix[c] for c in cats], dtype=np.float64)
    cat = cats[int(rng.choice(len(cats), p=w / w.sum()))]
    color = s.traffic.colors[int(rng.integers(len(s.traffic.colors)))]
    nouns = CATEGORY_NOUNS[cat]
    noun = nouns[int(rng.integers(len(nouns)))]
    return Appearance(cat, NAMED_COLORS[color], color, describe(cat, color, noun), CATEGORY_SIZES[cat])


def spawn_traffic(
    road: Road, layout: RoadLayout, s: Scenario, rng: np.random.Generator, cfg: PopulationConfig
) -> list[TrafficVehicle]:
    """``s.traffic.count`` IDM vehicles on the layout's spawn edges (fewer if the road is full).
    On the ego's road they fill a window around the ego whose length shrinks with density."""
    net = layout.network
    ego = road.vehicles[0]
    lanes = [(f, t, k) for f, t in layout.spawn_edges for k in range(len(net.graph[f][t]))]
    intervals = []
    for idx in lanes:
        lane = net.get_lane(idx)
        lo, hi = cfg.edge_margin_m, lane.length - cfg.edge_margin_m
        if idx[:2] == layout.ego_edge:
            n = len(net.graph[idx[0]][idx[1]])
            v_mean = np.mean(cfg.speed_fraction) * lane.speed_limit
            spacing = (cfg.base_spacing_m + v_mean) * math.exp(-cfg.lane_count_decay * n) / s.traffic.density
            window = spacing * s.traffic.count
            ego_s = lane.local_coordinates(ego.position)[0]
            lo, hi = (
                max(lo, ego_s - cfg.rear_fraction * window),
                min(hi, ego_s + (1 - cfg.rear_fraction) * window),
            )
        intervals.append((lo, hi))
    weights = np.array([max(hi - lo, 0.0) for lo, hi in intervals])
    out: list[TrafficVehicle] = []
    if weights.sum() <= 0:
        return out
    for i in range(s.traffic.count):
        look = _traffic_appearance(s, rng)
        for _ in range(cfg.attempts):
            k = int(rng.choice(len(lanes), p=weights / weights.sum()))
            lo, hi = intervals[k]
            lane = net.get_lane(lanes[k])
            x = float(rng.uniform(lo, hi))
            if _free(road, lane, x, look.size[0], cfg.clearance_m):
                break
        else:
            continue  # road too full here: drop this vehicle
        speed = float(rng.uniform(*cfg.speed_fraction)) * lane.speed_limit
        v = TrafficVehicle(road, lane.position(x, 0.0), lane.heading_at(x), speed)
        v.randomize_behavior()
        if layout.destinations:
            v.plan_route_to(layout.destinations[int(rng.integers(len(layout.destinations)))])
        _dress(v, f"idm_{i:03d}", look, scripted=False)
        road.vehicles.append(v)
        road.invalidate()
        out.append(v)
    return out


def _free(road: Road, lane: AbstractLane, x: float, length: float, clearance: float) -> bool:
    ents = [*road.vehicles, *road.objects]
    if not ents:
        return True
    pos = np.array([e.position for e in ents])
    s, r = lane_coordinates(lane, pos)
    half = np.array([e.LENGTH for e in ents]) / 2 + length / 2 + clearance
    return not np.any((np.abs(r) < lane.width_at(0)) & (np.abs(s - x) < half))


def _dress(obj: TrafficVehicle | ScriptedObject, track_id: str, look: Appearance, scripted: bool) -> None:
    obj.track_id, obj.appearance, obj.scripted = track_id, look, scripted
    size_object(obj, *look.size[:2])


def make_scripted(road: Road, layout: RoadLayout, spec: ObjectSpec, source: str) -> TrafficVehicle | ScriptedObject:
    """A scripted object: an IDM vehicle for ``lane_follow`` with mode idm, else a ScriptedObject."""
    from m4world_env.traffic.objects import spec_appearance

    try:
        if isinstance(spec.track, LaneFollowTrack) and spec.track.mode == "idm":
            path = LanePath(layout.network, (*layout.ego_edge, spec.track.lane))
            path.check_placed(spec.track.start, "start")
            x, y, h = path.pose(spec.track.start)
            v = TrafficVehicle(
                road, [x, y], h, spec.track.speed, target_speed=spec.track.speed, enable_lane_change=False
            )
            _dress(v, spec.id, spec_appearance(spec), scripted=True)
            v.spec = spec
            return v
        obj = ScriptedObject(road, spec, make_track(spec, layout.network, layout.ego_edge), 0.0)
        obj.scripted = True
        return obj
    except (ValueError, KeyError, IndexError) as err:
        raise ScenarioError(f"{source}: objects.{spec.id}.track: {err}") from None


def parse_spec(spec: object, source: str) -> ObjectSpec:
    if isinstance(spec, ObjectSpec):
        return spec
    from pydantic import ValidationError

    from m4world_env.scenario import _format_validation_error  # one formatting for all errors

    try:
        return ObjectSpec.model_validate(spec)
    except ValidationError as err:
        raise ScenarioError(_format_validation_error(source, err, spec)) from None


def departed(road: Road, ego: Vehicle, cfg: PopulationConfig) -> list:
    """IDM vehicles that drove past the end of a terminal lane (they would leave the map)."""
    out = []
    for v in road.vehicles:
        if v is ego or not is_vehicle(v):
            continue
        frm, to, _ = v.lane_index
        if road.network.graph.get(to):
            continue
        if v.lane.local_coordinates(v.position)[0] > v.lane.length + cfg.departure_margin_m:
            out.append(v)
    return out


def edit(
    road: Road, layout: RoadLayout, obj: TrafficVehicle | ScriptedObject, changes: dict
) -> TrafficVehicle | ScriptedObject:
    """Apply ``changes`` to ``obj``; returns the object to keep (a new one if the track changed).
    Raises :class:`ScenarioError` naming the field, and then changes nothing."""
    source = f"edit_object({obj.track_id})"
    bad = sorted(set(changes) - set(EDITABLE))
    if bad:
        raise ScenarioError(f"{source}: cannot edit {bad}; editable fields: {EDITABLE}")
    look = obj.appearance
    spec = getattr(obj, "spec", None)
    if "track" in changes:
        if spec is None:
            raise ScenarioError(
                f"{source}: track: {obj.track_id!r} is IDM traffic: it has no scripted track to replace"
            )
        data = {**spec.model_dump(), **changes}
        return make_scripted(road, layout, parse_spec(data, source), "edit_object")
    if "speed" in changes and not is_vehicle(obj):
        raise ScenarioError(
            f"{source}: speed: {obj.track_id!r} follows a scripted track: change its motion with track=..., not speed"
        )
    speed = _checked_speed(changes["speed"], source) if "speed" in changes else None  # before anything changes
    category = changes.get("category", look.category)
    probe = {
        "id": obj.track_id,
        "category": category,
        "color": changes.get("color", look.color_name),
        "description": changes.get("description", ""),
        "image": changes.get("image", look.image_path),
        "size": changes.get("size"),
        "track": {"kind": "static", "x": 0.0, "y": 0.0},
    }
    if isinstance(probe["color"], str) and probe["color"].startswith("rgb("):
        probe["color"] = look.color
    checked = parse_spec(probe, source)  # validates every appearance field
    keep_text = "description" not in changes and "category" not in changes and "color" not in changes
    new_look = Appearance(
        category=checked.category,
        color=checked.rgb,
        color_name=checked.color_name,
        description=look.description if keep_text else (checked.description or describe(category, checked.color_name)),
        size=checked.size
        if checked.size is not None
        else (look.size if "category" not in changes else CATEGORY_SIZES[category]),
        image_path=checked.image,
    )
    _dress(obj, obj.track_id, new_look, obj.scripted)
    if spec is not None:
        obj.spec = spec.model_copy(
            update={k: v for k, v in changes.items() if k in ("category", "color", "description", "image", "size")}
        )
    if speed is not None:
        obj.target_speed = speed
    road.invalidate()
    return obj


def _checked_speed(value: object, source: str) -> float:
    """A target speed, m/s, within the scenarios' speed bounds (bools and strings are not numbers)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0 <= value <= MAX_SPEED_MPS:
        raise ScenarioError(f"{source}: speed: must be a number in [0, {MAX_SPEED_MPS:g}] m/s, got {value!r}")
    return float(value)
