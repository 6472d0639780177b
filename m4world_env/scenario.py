"""Scenario files: what road, which traffic, which scripted objects, what the sky looks like.

A scenario is a YAML file validated by pydantic v2 models with ``extra="forbid"`` everywhere, so
a typo is an error, never a silently ignored key. Every load error is a :class:`ScenarioError`
whose message names the file and the field path (``scenarios/foo.yaml: objects.2.track.speed:
Input should be a valid number``). The format is documented in ``docs/scenarios.md``.

Coordinates in scenarios use OUR frame (x forward, y left, yaw counter-clockwise, metres). Lane
ids are highway-env's: lane 0 is the leftmost lane of a road in its driving direction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    Strict,
    ValidationError,
    field_validator,
    model_validator,
)

from world_model.scene import CATEGORIES, CATEGORY_SIZES, NAMED_COLORS, TIMES_OF_DAY, WEATHERS, ScenePrompt

SCENARIOS_DIR = Path(__file__).parent / "scenarios"

# Categories IDM traffic may be drawn from (they drive; pedestrians and cones do not).
VEHICLE_CATEGORIES = ("car", "truck", "bus", "van", "motorcycle", "tree_truck", "cement_mixer")
DEFAULT_TRAFFIC_MIX = {"car": 0.8, "truck": 0.06, "bus": 0.03, "van": 0.07, "motorcycle": 0.04}
DEFAULT_TRAFFIC_COLORS = ("white", "black", "gray", "silver", "red", "blue", "dark_red", "navy", "beige")

# Physical bounds of a scenario. Past them a file describes nothing a driving policy meets, and the
# road builder, the traffic or a step's frame count would run out of memory or time
# (docs/scenarios.md, "Bounds").
MAX_ROAD_LENGTH_M = 10_000.0  # any straight road, approach, arm or road section
MAX_LANE_WIDTH_M = 8.0
MAX_RADIUS_M = 500.0  # roundabout ring, turning lanes
MAX_SPEED_MPS = 90.0  # ~320 km/h: speed limits, the ego's and scripted objects' speeds
MIN_SPEED_LIMIT_MPS = 1.0  # walking pace; below it a road's target speeds and progress scale vanish
MAX_POSITION_M = 20_000.0  # |x|, |y|, positions and offsets along a lane
MAX_LATERAL_M = 20.0  # offset from a lane's centre
MAX_YAW_RAD = 4 * math.pi
MAX_DURATION_S = 3_600.0  # episode duration, waypoint and manoeuvre times
MIN_POLICY_FREQUENCY_HZ = 0.1
MAX_FREQUENCY_HZ = 100.0
MAX_FRAMES_PER_STEP = 20  # sensor frames per env step: one causal chunk of the world model
MAX_OBJECT_SIZE_M = 30.0
MIN_OBJECT_SIZE_M = 0.05  # a few centimetres: below it no camera pixel or LiDAR beam can see the box
MIN_LANE_CHANGE_S = 0.5  # a cut-in's lateral move; faster is a jump, not a manoeuvre
MIN_TRAFFIC_DENSITY = 0.01  # a hundredth of highway-env's spacing density: sparser is an empty road
MAX_TRAFFIC_DENSITY = 10.0
MAX_TRAFFIC_COUNT = 200
TIME_TOLERANCE = 1e-9  # float rounding in products and ratios of seconds and hertz
MAX_OBJECTS = 64
MAX_WAYPOINTS = 10_000

# Numbers must be written as numbers: YAML reads ``yes``/``true`` as booleans, which pydantic would
# otherwise take as 1 (``lanes: yes`` would build a one-lane road); ints stay ints (no 2.7 -> 2).
Float = Annotated[float, Strict()]
Int = Annotated[int, Strict()]
# Text must be written as text: pydantic would otherwise decode bytes (YAML's ``!!binary``) into a str.
Str = Annotated[str, Strict()]

Category = Literal[CATEGORIES]  # type: ignore[valid-type]
VehicleCategory = Literal[VEHICLE_CATEGORIES]  # type: ignore[valid-type]
Weather = Literal[WEATHERS]  # type: ignore[valid-type]
TimeOfDay = Literal[TIMES_OF_DAY]  # type: ignore[valid-type]


class ScenarioError(ValueError):
    """A scenario file or scenario value is invalid. The message names the file and field path."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)  # an inf speed would fail only mid-episode


def _check_color(value: str | tuple[int, int, int]) -> str | tuple[int, int, int]:
    if isinstance(value, str):
        if value not in NAMED_COLORS:
            raise ValueError(f"unknown colour {value!r}; use an RGB triple or one of {sorted(NAMED_COLORS)}")
        return value
    if len(value) != 3 or any(not 0 <= int(c) <= 255 for c in value):
        raise ValueError(f"RGB colour must be three integers in [0, 255], got {value!r}")
    return tuple(int(c) for c in value)


Color = Str | tuple[Int, Int, Int]

# ---------------------------------------------------------------------------------------- roads


class HighwayRoad(_Strict):
    """A straight multi-lane highway (highway-env's ``highway-v0`` road)."""

    type: Literal["highway"] = "highway"
    lanes: Int = Field(4, ge=1, le=8)
    length: Float = Field(2000.0, gt=50, le=MAX_ROAD_LENGTH_M)
    speed_limit: Float = Field(30.0, ge=MIN_SPEED_LIMIT_MPS, le=MAX_SPEED_MPS)
    lane_width: Float = Field(4.0, gt=2, le=MAX_LANE_WIDTH_M)

    @property
    def start_lanes(self) -> int:
        """Lanes of the edge the ego and lane-placed objects start on (what ``lane`` fields index)."""
        return self.lanes

    def length_along(self, lane: int) -> float:
        """Metres of road straight on from the start of start lane ``lane``: the farthest an ego may
        be placed on it (``ego.longitudinal``) and still stand on the road."""
        return self.length


class MergeRoad(_Strict):
    """A highway with an on-ramp joining from the right (``merge-v0``)."""

    type: Literal["merge"] = "merge"
    lanes: Int = Field(2, ge=1, le=6)
    before: Float = Field(150.0, gt=10, le=MAX_ROAD_LENGTH_M, description="main road before the ramp converges, m")
    converging: Float = Field(80.0, gt=10, le=MAX_ROAD_LENGTH_M, description="length of the ramp's S-curve, m")
    merge_length: Float = Field(80.0, gt=10, le=MAX_ROAD_LENGTH_M, description="length of the acceleration lane, m")
    after: Float = Field(800.0, gt=10, le=MAX_ROAD_LENGTH_M, description="main road after the merge, m")
    speed_limit: Float = Field(30.0, ge=MIN_SPEED_LIMIT_MPS, le=MAX_SPEED_MPS)
    ramp_speed_limit: Float = Field(20.0, ge=MIN_SPEED_LIMIT_MPS, le=MAX_SPEED_MPS)
    lane_width: Float = Field(4.0, gt=2, le=MAX_LANE_WIDTH_M)

    @property
    def start_lanes(self) -> int:
        """The main road before the ramp joins."""
        return self.lanes

    def length_along(self, lane: int) -> float:
        """The main road's whole length: it runs straight on past the ramp."""
        return self.before + self.converging + self.merge_length + self.after


class RoundaboutRoad(_Strict):
    """A four-arm roundabout, counter-clockwise (right-hand traffic)."""

    type: Literal["roundabout"] = "roundabout"
    radius: Float = Field(20.0, ge=8, le=MAX_RADIUS_M, description="radius of the inner ring lane, m")
    lanes: Int = Field(2, ge=1, le=3, description="ring lanes")
    access_length: Float = Field(150.0, gt=20, le=MAX_ROAD_LENGTH_M, description="length of each straight approach, m")
    entry_angle_deg: Float = Field(24.0, gt=5, lt=40, description="half-angle between entry and exit")
    speed_limit: Float = Field(12.0, ge=MIN_SPEED_LIMIT_MPS, le=MAX_SPEED_MPS)
    lane_width: Float = Field(4.0, gt=2, le=MAX_LANE_WIDTH_M)

    @property
    def start_lanes(self) -> int:
        """The south approach is one lane (``lanes`` counts the ring's)."""
        return 1

    def length_along(self, lane: int) -> float:
        """The straight approach; past it the road bends onto the ring."""
        return self.access_length


class IntersectionRoad(_Strict):
    """A four-arm unsignalized crossing, one lane per direction, with turning lanes."""

    type: Literal["intersection"] = "intersection"
    arm_length: Float = Field(100.0, gt=20, le=MAX_ROAD_LENGTH_M)
    turn_radius: Float = Field(10.0, ge=4, le=MAX_RADIUS_M, description="radius of the right-turn lanes, m")
    speed_limit: Float = Field(12.0, ge=MIN_SPEED_LIMIT_MPS, le=MAX_SPEED_MPS)
    lane_width: Float = Field(4.0, gt=2, le=MAX_LANE_WIDTH_M)

    @property
    def start_lanes(self) -> int:
        """One lane per direction: the south arm's incoming lane."""
        return 1

    def length_along(self, lane: int) -> float:
        """The south arm up to the crossing."""
        return self.arm_length


class TwoWayRoad(_Strict):
    """A straight road with oncoming traffic on the left (``two-way-v0``)."""

    type: Literal["two_way"] = "two_way"
    lanes: Int = Field(1, ge=1, le=4, description="lanes in the ego's direction")
    oncoming_lanes: Int = Field(1, ge=1, le=4)
    length: Float = Field(1000.0, gt=50, le=MAX_ROAD_LENGTH_M)
    speed_limit: Float = Field(20.0, ge=MIN_SPEED_LIMIT_MPS, le=MAX_SPEED_MPS)
    lane_width: Float = Field(4.0, gt=2, le=MAX_LANE_WIDTH_M)

    @property
    def start_lanes(self) -> int:
        """The ego's direction (oncoming lanes are not lane-addressable)."""
        return self.lanes

    def length_along(self, lane: int) -> float:
        return self.length


Point = tuple[
    Annotated[Float, Field(ge=-MAX_POSITION_M, le=MAX_POSITION_M)],
    Annotated[Float, Field(ge=-MAX_POSITION_M, le=MAX_POSITION_M)],
]


def _polyline_length(points: list[tuple[float, float]]) -> float:
    return float(np.hypot(*np.diff(np.asarray(points, dtype=np.float64), axis=0).T).sum())


def _check_polyline(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    p = np.asarray(points, dtype=np.float64)
    if _polyline_length(points) > MAX_ROAD_LENGTH_M:
        raise ValueError(f"a polyline may be at most {MAX_ROAD_LENGTH_M:g} m long")
    if np.all(np.hypot(*(p - p[0]).T) < 1e-3):
        raise ValueError("a polyline needs at least two distinct points")
    return points


PolylinePoints = Annotated[list[Point], Field(min_length=2, max_length=MAX_WAYPOINTS), AfterValidator(_check_polyline)]


class RouteLaneLine(_Strict):
    kind: Literal["solid", "dashed"]
    points: PolylinePoints


class RouteMap(_Strict):
    """Map geometry drawn around a route road (and, with ``drivable_area``, what on-road means)."""

    drivable_area: list[Annotated[list[Point], Field(min_length=3, max_length=MAX_WAYPOINTS)]] = Field(
        default_factory=list, max_length=MAX_OBJECTS, description="polygons; their union is the road"
    )
    lane_lines: list[RouteLaneLine] = Field(default_factory=list, max_length=4 * MAX_OBJECTS)
    road_edges: list[PolylinePoints] = Field(default_factory=list, max_length=MAX_OBJECTS)


class RouteRoad(_Strict):
    """Lanes along polylines (log replay): the ego's lanes follow ``lanes``; ``reference_path`` is
    the path the ego is scored along (its logged path)."""

    type: Literal["route"] = "route"
    source: Literal["map_expansion", "ego_path"] = Field(
        ..., description="what the lanes were made from: a map's lane centerlines or the logged ego path"
    )
    lanes: list[PolylinePoints] = Field(
        ..., min_length=1, max_length=8, description="lane centerlines, leftmost first, all in the driving direction"
    )
    reference_path: PolylinePoints = Field(..., description="the path progress is measured along (the logged one)")
    speed_limit: Float = Field(..., ge=MIN_SPEED_LIMIT_MPS, le=MAX_SPEED_MPS)
    lane_width: Float = Field(4.0, gt=2, le=MAX_LANE_WIDTH_M)
    map: RouteMap | None = Field(None, description="drawn map and drivable area; absent: the lanes' strips")

    @property
    def start_lanes(self) -> int:
        """Every lane runs the route's whole length."""
        return len(self.lanes)

    def length_along(self, lane: int) -> float:
        """The lane's centerline."""
        return _polyline_length(self.lanes[lane])


Road = Annotated[
    HighwayRoad | MergeRoad | RoundaboutRoad | IntersectionRoad | TwoWayRoad | RouteRoad, Field(discriminator="type")
]

# ------------------------------------------------------------------------------ ego and traffic


class EgoSpec(_Strict):
    lane: Int = Field(1, ge=0, description="lane id on the road's start edge (0 = leftmost)")
    longitudinal: Float = Field(30.0, ge=0, le=MAX_POSITION_M, description="position along the start lane, m")
    speed: Float = Field(25.0, ge=0, le=MAX_SPEED_MPS)
    turn: Literal["left", "straight", "right"] = Field(
        "straight", description="route at a roundabout or intersection (ignored on straight roads)"
    )


class TrafficSpec(_Strict):
    count: Int = Field(10, ge=0, le=MAX_TRAFFIC_COUNT)
    density: Float = Field(
        1.0,
        ge=MIN_TRAFFIC_DENSITY,
        le=MAX_TRAFFIC_DENSITY,
        description="1 = highway-env's default spacing; 2 = twice as dense",
    )
    mix: dict[VehicleCategory, Float] = Field(default_factory=lambda: dict(DEFAULT_TRAFFIC_MIX))
    colors: list[Str] = Field(default_factory=lambda: list(DEFAULT_TRAFFIC_COLORS), min_length=1)

    @field_validator("mix")
    @classmethod
    def _mix_positive(cls, mix: dict[str, float]) -> dict[str, float]:
        # Each weight is finite (allow_inf_nan); their sum must be too, or the normalized mix is NaN.
        total = sum(mix.values())
        if not mix or any(w < 0 for w in mix.values()) or not 0 < total < math.inf:
            raise ValueError(f"mix needs non-negative weights whose sum is finite and positive, got {mix}")
        return mix

    @field_validator("colors")
    @classmethod
    def _named_colors(cls, colors: list[str]) -> list[str]:
        for c in colors:
            _check_color(c)
        return colors


# ----------------------------------------------------------------------------- scripted tracks


class StaticTrack(_Strict):
    """Standing still, either on a lane (``lane`` + ``longitudinal``) or at ``x``/``y``/``yaw``."""

    kind: Literal["static"] = "static"
    lane: Int | None = Field(None, ge=0)
    longitudinal: Float | None = Field(None, ge=-MAX_POSITION_M, le=MAX_POSITION_M)
    x: Float | None = Field(None, ge=-MAX_POSITION_M, le=MAX_POSITION_M)
    y: Float | None = Field(None, ge=-MAX_POSITION_M, le=MAX_POSITION_M)
    yaw: Float = Field(0.0, ge=-MAX_YAW_RAD, le=MAX_YAW_RAD)
    lateral: Float = Field(
        0.0,
        ge=-MAX_LATERAL_M,
        le=MAX_LATERAL_M,
        description="offset to the LEFT of the lane centre, m (lane placement only)",
    )

    @model_validator(mode="after")
    def _one_placement(self) -> StaticTrack:
        on_lane = self.lane is not None and self.longitudinal is not None
        at_xy = self.x is not None and self.y is not None
        if on_lane == at_xy:
            raise ValueError("give either lane + longitudinal, or x + y (and optionally yaw)")
        return self


class LaneFollowTrack(_Strict):
    """Drives along a lane from ``start``: constant speed, or IDM (brakes for what is ahead)."""

    kind: Literal["lane_follow"] = "lane_follow"
    lane: Int = Field(..., ge=0)
    start: Float = Field(0.0, ge=-MAX_POSITION_M, le=MAX_POSITION_M)
    speed: Float = Field(..., ge=0, le=MAX_SPEED_MPS)
    mode: Literal["constant", "idm"] = "constant"


class Waypoint(_Strict):
    t: Float = Field(..., ge=0, le=MAX_DURATION_S)
    x: Float = Field(..., ge=-MAX_POSITION_M, le=MAX_POSITION_M)
    y: Float = Field(..., ge=-MAX_POSITION_M, le=MAX_POSITION_M)
    yaw: Float | None = Field(None, ge=-MAX_YAW_RAD, le=MAX_YAW_RAD, description="omitted: the direction of motion")


class WaypointsTrack(_Strict):
    """Timed poses in our frame, linearly interpolated; holds the last pose afterwards."""

    kind: Literal["waypoints"] = "waypoints"
    points: list[Waypoint] = Field(..., min_length=2, max_length=MAX_WAYPOINTS)

    @field_validator("points")
    @classmethod
    def _increasing(cls, pts: list[Waypoint]) -> list[Waypoint]:
        if any(b.t <= a.t for a, b in zip(pts, pts[1:], strict=False)):
            raise ValueError("waypoint times must be strictly increasing")
        return pts


class CutInTrack(_Strict):
    """Drives in ``from_lane`` at ``speed`` and moves to ``to_lane`` between ``time`` and
    ``time + duration`` (a smooth cosine lateral profile)."""

    kind: Literal["cut_in"] = "cut_in"
    from_lane: Int = Field(..., ge=0)
    to_lane: Int = Field(..., ge=0)
    start: Float = Field(0.0, ge=-MAX_POSITION_M, le=MAX_POSITION_M)
    speed: Float = Field(..., ge=0, le=MAX_SPEED_MPS)
    time: Float = Field(..., ge=0, le=MAX_DURATION_S)
    duration: Float = Field(2.0, ge=MIN_LANE_CHANGE_S, le=MAX_DURATION_S)


Track = Annotated[StaticTrack | LaneFollowTrack | WaypointsTrack | CutInTrack, Field(discriminator="kind")]


class ObjectSpec(_Strict):
    """One scripted object."""

    id: Str = Field(..., min_length=1)
    category: Category
    color: Color = "gray"
    description: Str = ""
    image: Str | None = None
    size: tuple[Float, Float, Float] | None = Field(None, description="length, width, height; default by category")
    track: Track

    @field_validator("color")
    @classmethod
    def _color(cls, v: Color) -> Color:
        return _check_color(v)

    @field_validator("image")
    @classmethod
    def _image(cls, v: str | None) -> str | None:
        if v is not None and not Path(v).is_file():
            raise ValueError(f"image file {v!r} not found (relative paths start at the working directory)")
        return v

    @field_validator("size")
    @classmethod
    def _size(cls, v: tuple[Float, Float, Float] | None) -> tuple[Float, Float, Float] | None:
        if v is not None and any(not (math.isfinite(s) and MIN_OBJECT_SIZE_M <= s <= MAX_OBJECT_SIZE_M) for s in v):
            raise ValueError(f"size must be three lengths in [{MIN_OBJECT_SIZE_M:g}, {MAX_OBJECT_SIZE_M:g}] m, got {v}")
        return v

    @property
    def box_size(self) -> tuple[float, float, float]:
        return self.size if self.size is not None else CATEGORY_SIZES[self.category]

    @property
    def rgb(self) -> tuple[int, int, int]:
        return NAMED_COLORS[self.color] if isinstance(self.color, str) else self.color

    @property
    def color_name(self) -> str:
        return self.color if isinstance(self.color, str) else "rgb({}, {}, {})".format(*self.color)


# -------------------------------------------------------------------------------- the scenario


class Scenario(_Strict):
    name: Str = Field(..., min_length=1)
    road: Road
    duration: Float = Field(30.0, gt=0, le=MAX_DURATION_S, description="seconds")
    policy_frequency: Float = Field(
        5.0, ge=MIN_POLICY_FREQUENCY_HZ, le=MAX_FREQUENCY_HZ, description="agent decisions per second"
    )
    sensor_frequency: Float = Field(10.0, gt=0, le=MAX_FREQUENCY_HZ, description="sensor frames per second")
    substeps: Int = Field(1, ge=1, le=20, description="simulation steps per sensor frame")
    prompt_text: Str = Field("", alias="prompt")
    weather: Weather = "sunny"
    time_of_day: TimeOfDay = "day"
    ego: EgoSpec = Field(default_factory=EgoSpec)
    traffic: TrafficSpec = Field(default_factory=TrafficSpec)
    objects: list[ObjectSpec] = Field(default_factory=list, max_length=MAX_OBJECTS)
    adapters: list[Str] = Field(
        default_factory=list, description="LoRA adapter names or paths; each goes into the model it was trained on"
    )

    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    @model_validator(mode="after")
    def _consistent(self) -> Scenario:
        ratio = self.sensor_frequency / self.policy_frequency
        if abs(ratio - round(ratio)) > TIME_TOLERANCE or not 1 <= round(ratio) <= MAX_FRAMES_PER_STEP:
            raise ValueError(
                f"sensor_frequency / policy_frequency (sensor frames per env step) must be an integer in "
                f"[1, {MAX_FRAMES_PER_STEP}], got {self.sensor_frequency} / {self.policy_frequency}"
            )
        ids = [o.id for o in self.objects]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ValueError(f"object ids must be unique, duplicated: {dup}")
        return self

    @property
    def frames_per_step(self) -> int:
        """Sensor frames per env step (one causal chunk)."""
        return round(self.sensor_frequency / self.policy_frequency)

    @property
    def num_steps(self) -> int:
        """Env steps in ``duration``."""
        return max(1, math.ceil(self.duration * self.policy_frequency - TIME_TOLERANCE))

    @property
    def sim_dt(self) -> float:
        """Seconds per simulation substep."""
        return 1.0 / (self.sensor_frequency * self.substeps)

    def prompt(self) -> ScenePrompt:
        return ScenePrompt(text=self.prompt_text, weather=self.weather, time_of_day=self.time_of_day)


# ------------------------------------------------------------------------------------- loading


def _yaml_path(loc: tuple, data: object) -> str:
    """pydantic's error location as a path in the user's YAML: union tags are dropped."""
    parts, cur = [], data
    for p in loc:
        in_dict = isinstance(cur, dict) and p in cur
        if in_dict or (isinstance(cur, list) and isinstance(p, int) and 0 <= p < len(cur)):
            cur = cur[p]
        elif isinstance(cur, dict) and p in (cur.get("type"), cur.get("kind")):
            continue  # the discriminated-union branch pydantic went into, not a YAML key
        elif isinstance(p, str) and p[:1].isupper():
            continue  # a model-class branch of a plain union
        else:
            cur = None
        parts.append(str(p))
    return ".".join(parts) or "<root>"


MAX_SHOWN_VALUE_CHARS = 80  # a refused value is quoted in the message up to this length


def _shown_value(error: dict) -> str:
    """ ", got <value>" for an error about one value (not about a mapping or list, where the value
    would be the whole subtree, nor about a missing key, where it is the parent)."""
    value = error.get("input")
    if error["type"] == "missing" or isinstance(value, dict | list):
        return ""
    text = repr(value)
    return f", got {text if len(text) <= MAX_SHOWN_VALUE_CHARS else text[:MAX_SHOWN_VALUE_CHARS] + '...'}"


def _format_validation_error(source: str, err: ValidationError, data: object = None) -> str:
    return "\n".join(f"{source}: {_yaml_path(e['loc'], data)}: {e['msg']}{_shown_value(e)}" for e in err.errors())


def scenario_from_dict(data: object, source: str = "<dict>") -> Scenario:
    """Validate a parsed scenario mapping. Raises :class:`ScenarioError` naming ``source``."""
    if not isinstance(data, dict):
        raise ScenarioError(f"{source}: <root>: a scenario must be a mapping, got {type(data).__name__}")
    try:
        scenario = Scenario.model_validate(data)
    except ValidationError as err:
        raise ScenarioError(_format_validation_error(source, err, data)) from None
    _check_lanes(scenario, source)
    _check_extents(scenario, source)
    return scenario


def _lane_fields(scenario: Scenario) -> list[tuple[str, int]]:
    """(YAML path, lane id) of every field that indexes a lane of the road's start edge."""
    fields = [("ego.lane", scenario.ego.lane)]
    for i, obj in enumerate(scenario.objects):
        for name in ("lane", "from_lane", "to_lane"):
            lane = getattr(obj.track, name, None)
            if lane is not None:
                fields.append((f"objects.{i}.track.{name}", lane))
    return fields


def _check_lanes(scenario: Scenario, source: str) -> None:
    """Lane ids must exist on the start edge (caught at load, naming the file, not at reset)."""
    n = scenario.road.start_lanes
    errors = [
        f"{source}: {path}: lane {lane} does not exist; the {scenario.road.type} road starts with {n} "
        f"lane{'s' if n > 1 else ''} (0 = leftmost)"
        for path, lane in _lane_fields(scenario)
        if lane >= n
    ]
    if errors:
        raise ScenarioError("\n".join(errors))


def _check_extents(scenario: Scenario, source: str) -> None:
    """Bounds that involve two fields: an episode lasts at least one policy step, and the ego
    starts on the road (its lane must exist: after :func:`_check_lanes`)."""
    errors = []
    step_s = 1.0 / scenario.policy_frequency
    if scenario.duration * scenario.policy_frequency < 1.0 - TIME_TOLERANCE:
        errors.append(
            f"{source}: duration: {scenario.duration!r} s is shorter than one policy step "
            f"(1 / policy_frequency = {step_s:g} s)"
        )
    ego, road = scenario.ego, scenario.road
    length = road.length_along(ego.lane)
    if ego.longitudinal > length:
        errors.append(
            f"{source}: ego.longitudinal: {ego.longitudinal!r} m is past the road's end; the {road.type} road "
            f"runs {length:g} m along lane {ego.lane} from where the ego starts"
        )
    if errors:
        raise ScenarioError("\n".join(errors))


MAX_FILE_BYTES = 1_000_000  # a scenario is a page of YAML; this bounds parsing time and memory


class _StrictYamlLoader(yaml.SafeLoader):
    """YAML's safe subset, refusing duplicate keys (the last one would silently win)."""


def _construct_unique_mapping(loader: _StrictYamlLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    seen: set[Any] = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=True)
        try:
            duplicate = key in seen
        except TypeError:
            raise yaml.constructor.ConstructorError(
                None, None, f"a mapping key must be a plain value, got {type(key).__name__}", key_node.start_mark
            ) from None
        if duplicate:
            raise yaml.constructor.ConstructorError(None, None, f"duplicate key {key!r}", key_node.start_mark)
        seen.add(key)
    return loader.construct_mapping(node, deep=deep)


_StrictYamlLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_unique_mapping)


def _resolve(name_or_path: str | Path) -> Path:
    if not isinstance(name_or_path, str | Path):
        raise ScenarioError(
            f"scenario must be a bundled scenario name or a path to a YAML file, got {type(name_or_path).__name__}"
        )
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        if not p.exists():
            raise ScenarioError(f"{p}: no such scenario file")
        if not p.is_file():
            raise ScenarioError(f"{p}: a scenario must be a YAML file, not a directory")
        return p
    bundled = SCENARIOS_DIR / f"{name_or_path}.yaml"
    if not bundled.exists():
        raise ScenarioError(f"unknown scenario {str(name_or_path)!r}; bundled ones: {', '.join(list_scenarios())}")
    return bundled


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a bundled scenario by name (``"merge_cut_in"``) or any YAML file by path."""
    path = _resolve(name_or_path)
    raw = path.read_bytes()
    if len(raw) > MAX_FILE_BYTES:
        raise ScenarioError(f"{path}: {len(raw)} bytes; a scenario file may have at most {MAX_FILE_BYTES}")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ScenarioError(f"{path}: not UTF-8 text (byte {err.start}: {raw[err.start : err.start + 1]!r})") from None
    try:
        data = yaml.load(text, Loader=_StrictYamlLoader)  # noqa: S506 - a SafeLoader subclass
    except RecursionError:
        raise ScenarioError(f"{path}: YAML nested too deeply to be a scenario") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark is not None else "<unknown position>"
        problem = getattr(err, "problem", None) or str(err)
        raise ScenarioError(f"{path}: YAML syntax error at {where}: {problem}") from None
    return scenario_from_dict(data, str(path))


def list_scenarios() -> list[str]:
    """Names of the bundled scenarios, sorted."""
    return sorted(p.stem for p in SCENARIOS_DIR.glob("*.yaml"))


@dataclass(frozen=True)
class RandomizationConfig:
    """Ranges of :func:`randomize_scenario`."""

    density_scale: tuple[float, float] = (0.6, 1.6)  # multiplies the scenario's density
    count_scale_max: Float = 2.0  # count drawn in [0, count_scale_max * count]
    empty_count_max: Int = 8  # an empty scenario gets up to this many vehicles
    mix_concentration: Float = 0.5  # Dirichlet alpha of the random category weights
    car_bias: Float = 2.0  # added to the car weight so that traffic stays mostly cars
    min_colors: Int = 3


def randomize_scenario(
    s: Scenario, rng: np.random.Generator, config: RandomizationConfig = RandomizationConfig()
) -> Scenario:
    """Seeded variation for data recording: traffic count/density, IDM categories and colours,
    weather and time of day. Road, ego and scripted objects are kept (they define the case)."""
    weights = rng.dirichlet(np.full(len(VEHICLE_CATEGORIES), config.mix_concentration))
    mix = {c: float(w) for c, w in zip(VEHICLE_CATEGORIES, weights, strict=True)}
    mix["car"] += config.car_bias
    for c, w in s.traffic.mix.items():
        mix[c] += w
    n_colors = int(rng.integers(config.min_colors, len(NAMED_COLORS) + 1))
    colors = [str(c) for c in rng.choice(sorted(NAMED_COLORS), size=n_colors, replace=False)]
    top = round(config.count_scale_max * s.traffic.count) if s.traffic.count else config.empty_count_max
    # Drawn first, then kept within the scenario's bounds (the draws stay those of every scenario).
    count = min(int(rng.integers(0, top + 1)), MAX_TRAFFIC_COUNT)
    density = s.traffic.density * rng.uniform(*config.density_scale)
    traffic = s.traffic.model_copy(
        update={
            "count": count,
            "density": float(min(max(density, MIN_TRAFFIC_DENSITY), MAX_TRAFFIC_DENSITY)),
            "mix": mix,
            "colors": colors,
        }
    )
    return s.model_copy(
        update={
            "traffic": traffic,
            "weather": str(rng.choice(WEATHERS)),
            "time_of_day": str(rng.choice(TIMES_OF_DAY)),
        }
    )
