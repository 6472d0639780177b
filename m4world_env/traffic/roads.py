"""Road networks built from highway-env's public blocks, parameterized by the scenario's road.

All geometry here is in highway-env's frame (x forward, y to the driver's RIGHT, heading
clockwise); the bridge converts to ours. Conventions: a lane's ``line_types[0]`` is its left
side (lateral < 0), ``line_types[1]`` its right side; lane 0 of an edge is the leftmost.
Traffic is right-hand: roundabouts run counter-clockwise in our frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from highway_env.road.lane import AbstractLane, CircularLane, LineType, SineLane, StraightLane
from highway_env.road.road import LaneIndex, RoadNetwork

from m4world_env.scenario import HighwayRoad, IntersectionRoad, MergeRoad, RoundaboutRoad, RouteRoad, TwoWayRoad
from m4world_env.traffic.polyline import PolylineLane
from m4world_env.traffic.sim import FastNetwork
from world_model.scene import LaneLine, MapGeometry

C, S, N = LineType.CONTINUOUS_LINE, LineType.STRIPED, LineType.NONE

# Arms of junctions, named in our frame (the ego comes from the south, driving north = +x).
# Values are the arm's outward direction as a highway-env angle, in the order the
# counter-clockwise ring visits them (highway-env angle decreasing).
ARMS = {"east": 90.0, "north": 0.0, "west": -90.0, "south": -180.0}
EGO_ARM = "south"
TURN_TARGET = {"right": "east", "straight": "north", "left": "west"}  # as seen from the south arm


@dataclass
class RoadLayout:
    """A built network plus what the bridge needs to populate it."""

    network: RoadNetwork
    ego_edge: tuple[str, str]  # the edge of the ego's start lane and of lane-placed objects
    spawn_edges: list[tuple[str, str]]  # IDM traffic spawns on these edges
    destinations: list[str] = field(default_factory=list)  # route end nodes (empty: follow the road)
    ego_destination: str | None = None
    lane_width: float = AbstractLane.DEFAULT_WIDTH
    # (lane index, side) pairs whose boundary is shared with other lanes, so not a road edge.
    inner_sides: set[tuple[LaneIndex, int]] = field(default_factory=set)
    # A map drawn instead of the lanes' own strips and markings (our frame), and the polygons whose
    # union is the road for the on-road test (empty: on a lane is on the road).
    map: MapGeometry | None = None
    drivable_area: tuple[np.ndarray, ...] = ()


def _lines(k: int, n: int) -> tuple[int, int]:
    """Markings of lane k of an n-lane carriageway: solid outside, dashed between lanes."""
    return (C if k == 0 else S, C if k == n - 1 else N)


def _unit(deg: float) -> np.ndarray:
    return np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg))])


def build_highway(road: HighwayRoad) -> RoadLayout:
    net = FastNetwork()
    w = road.lane_width
    for k in range(road.lanes):
        net.add_lane(
            "start",
            "end",
            StraightLane(
                [0.0, k * w],
                [road.length, k * w],
                width=w,
                line_types=_lines(k, road.lanes),
                speed_limit=road.speed_limit,
            ),
        )
    return RoadLayout(net, ("start", "end"), [("start", "end")], lane_width=w)


def build_merge(road: MergeRoad) -> RoadLayout:
    """Main road a-b-c-d; the ramp j-k-b runs parallel on the right, S-curves in, and becomes the
    rightmost lane of b-c (an acceleration lane that ends at c)."""
    net = FastNetwork()
    w, n = road.lane_width, road.lanes
    xb = road.before + road.converging
    xc, xd = xb + road.merge_length, xb + road.merge_length + road.after
    for k in range(n):
        lt = _lines(k, n)
        net.add_lane("a", "b", StraightLane([0, k * w], [xb, k * w], w, lt, speed_limit=road.speed_limit))
        # Along the acceleration lane the right marking becomes dashed.
        lt_merge = (lt[0], S if k == n - 1 else lt[1])
        net.add_lane("b", "c", StraightLane([xb, k * w], [xc, k * w], w, lt_merge, speed_limit=road.speed_limit))
        net.add_lane("c", "d", StraightLane([xc, k * w], [xd, k * w], w, lt, speed_limit=road.speed_limit))
    # Ramp: starts one lane-gap right of the main road's right edge, S-curves onto lane n.
    gap = w  # one lane width of verge between the ramp and the road before converging
    y_ramp, y_acc = n * w + gap, n * w
    amp = 0.5 * (y_ramp - y_acc)
    ramp = StraightLane(
        [0, y_ramp], [road.before, y_ramp], w, (C, C), forbidden=True, speed_limit=road.ramp_speed_limit
    )
    mid = 0.5 * (y_ramp + y_acc)
    curve = SineLane(
        [road.before, mid],
        [xb, mid],
        amp,
        math.pi / road.converging,
        math.pi / 2,
        w,
        [C, C],
        forbidden=True,
        speed_limit=road.ramp_speed_limit,
    )
    acc = StraightLane([xb, y_acc], [xc, y_acc], w, (N, C), forbidden=True, speed_limit=road.ramp_speed_limit)
    net.add_lane("j", "k", ramp)
    net.add_lane("k", "b", curve)
    net.add_lane("b", "c", acc)
    return RoadLayout(net, ("a", "b"), [("a", "b"), ("j", "k"), ("c", "d")], lane_width=w)


def _sine_between(
    start: np.ndarray,
    end_long: float,
    heading: np.ndarray,
    lat0: float,
    lat1: float,
    w: float,
    speed_limit: float,
) -> SineLane:
    """A lane along ``heading`` from longitudinal 0 at ``start`` to ``end_long``, whose lateral
    offset moves smoothly (half a sine period, zero slope at both ends) from lat0 to lat1."""
    lat_dir = np.array([-heading[1], heading[0]])
    mid, amp = 0.5 * (lat0 + lat1), 0.5 * (lat1 - lat0)
    a = start + lat_dir * mid
    b = a + heading * end_long
    return SineLane(a, b, amp, math.pi / end_long, -math.pi / 2, w, [N, N], speed_limit=speed_limit)


def build_roundabout(road: RoundaboutRoad) -> RoadLayout:
    net = FastNetwork()
    w, n = road.lane_width, road.lanes
    radii = [road.radius + k * w for k in range(n)]
    names = list(ARMS)
    _add_ring(net, road, radii)
    inner: set = set()
    for arm, theta in ARMS.items():
        inner |= _add_arm(net, road, arm, theta, radii[-1])
    spawn = [(f"{a}_far", f"{a}_mid") for a in ARMS] + [
        (f"ring_in_{a}", f"ring_out_{b}") for a, b in zip(names, names[1:] + names[:1], strict=True)
    ]
    dests = [f"{a}_exit_far" for a in ARMS]
    return RoadLayout(net, (f"{EGO_ARM}_far", f"{EGO_ARM}_mid"), spawn, dests, dests[0], w, inner)


def _add_ring(net: FastNetwork, road: RoundaboutRoad, radii: list[float]) -> None:
    """The ring's lanes, one per radius: for each arm, entry node at (theta - alpha), exit node at
    (theta + alpha); angles are unwrapped so every arc runs with decreasing highway-env angle."""
    w, alpha, n = road.lane_width, road.entry_angle_deg, road.lanes
    names = list(ARMS)
    for i, arm in enumerate(names):
        theta = ARMS[arm]
        nxt = names[(i + 1) % len(names)]
        theta_next = theta - 90.0
        for k, r in enumerate(radii):
            lt = _lines(k, n)
            arcs = [
                (f"ring_out_{arm}", f"ring_in_{arm}", theta + alpha, theta - alpha),
                (f"ring_in_{arm}", f"ring_out_{nxt}", theta - alpha, theta_next + alpha),
            ]
            for a, b, p0, p1 in arcs:
                net.add_lane(
                    a,
                    b,
                    CircularLane(
                        [0, 0],
                        r,
                        math.radians(p0),
                        math.radians(p1),
                        clockwise=False,
                        width=w,
                        line_types=lt,
                        speed_limit=road.speed_limit,
                    ),
                )


def _add_arm(net: FastNetwork, road: RoundaboutRoad, arm: str, theta: float, r_out: float) -> set:
    """One arm's approach (straight, then an S-curve onto the outer ring lane at ``r_out``) and its
    exit, mirroring it; the arm's straight lanes, which are inner lanes of the layout."""
    w, alpha = road.lane_width, road.entry_angle_deg
    sine_len = road.radius
    u = _unit(theta)
    lat_ring = r_out * math.sin(math.radians(alpha))
    long_ring = r_out * math.cos(math.radians(alpha))
    d_mid = long_ring + sine_len
    d_far = d_mid + road.access_length
    inward, inward_lat = -u, np.array([u[1], -u[0]])
    net.add_lane(
        f"{arm}_far",
        f"{arm}_mid",
        StraightLane(
            u * d_far + inward_lat * w / 2,
            u * d_mid + inward_lat * w / 2,
            w,
            (C, C),
            speed_limit=road.speed_limit,
        ),
    )
    net.add_lane(
        f"{arm}_mid",
        f"ring_in_{arm}",
        _sine_between(u * d_mid, sine_len, inward, w / 2, lat_ring, w, road.speed_limit),
    )
    outward_lat = np.array([-u[1], u[0]])
    net.add_lane(
        f"ring_out_{arm}",
        f"{arm}_exit_mid",
        _sine_between(u * long_ring, sine_len, u, lat_ring, w / 2, w, road.speed_limit),
    )
    net.add_lane(
        f"{arm}_exit_mid",
        f"{arm}_exit_far",
        StraightLane(
            u * d_mid + outward_lat * w / 2,
            u * d_far + outward_lat * w / 2,
            w,
            (N, C),
            speed_limit=road.speed_limit,
        ),
    )
    return {((f"{arm}_far", f"{arm}_mid", 0), 0), ((f"{arm}_exit_mid", f"{arm}_exit_far", 0), 0)}


def _arc(p: np.ndarray, heading: float, turn: str, radius: float, w: float, speed_limit: float) -> CircularLane:
    """A quarter circle starting at ``p`` with ``heading``; a right turn increases the
    highway-env heading (its y axis points right)."""
    if turn == "right":
        c = p + radius * np.array([math.cos(heading + math.pi / 2), math.sin(heading + math.pi / 2)])
        start = heading - math.pi / 2
        return CircularLane(c, radius, start, start + math.pi / 2, True, w, [N, N], speed_limit=speed_limit)
    c = p + radius * np.array([math.cos(heading - math.pi / 2), math.sin(heading - math.pi / 2)])
    start = heading + math.pi / 2
    return CircularLane(c, radius, start, start - math.pi / 2, False, w, [N, N], speed_limit=speed_limit)


def build_intersection(road: IntersectionRoad) -> RoadLayout:
    net = FastNetwork()
    w, v = road.lane_width, road.speed_limit
    half = road.turn_radius + w / 2  # half-size of the crossing box
    far = half + road.arm_length
    names = list(ARMS)
    inner: set = set()
    for arm, theta in ARMS.items():
        u = _unit(theta)
        in_lat, out_lat = np.array([u[1], -u[0]]), np.array([-u[1], u[0]])
        net.add_lane(
            f"{arm}_in_far",
            f"{arm}_in_near",
            StraightLane(u * far + in_lat * w / 2, u * half + in_lat * w / 2, w, (C, C), speed_limit=v),
        )
        net.add_lane(
            f"{arm}_out_near",
            f"{arm}_out_far",
            StraightLane(u * half + out_lat * w / 2, u * far + out_lat * w / 2, w, (N, C), speed_limit=v),
        )
        inner |= {((f"{arm}_in_far", f"{arm}_in_near", 0), 0), ((f"{arm}_out_near", f"{arm}_out_far", 0), 0)}
    for i, arm in enumerate(names):
        u = _unit(ARMS[arm])
        p = u * half + np.array([u[1], -u[0]]) * w / 2
        heading = math.radians(ARMS[arm]) + math.pi
        opposite, right, left = names[(i + 2) % 4], names[(i + 1) % 4], names[(i + 3) % 4]
        q = -u * half + np.array([u[1], -u[0]]) * w / 2
        net.add_lane(f"{arm}_in_near", f"{opposite}_out_near", StraightLane(p, q, w, (N, N), speed_limit=v))
        net.add_lane(f"{arm}_in_near", f"{right}_out_near", _arc(p, heading, "right", half - w / 2, w, v))
        net.add_lane(f"{arm}_in_near", f"{left}_out_near", _arc(p, heading, "left", half + w / 2, w, v))
    spawn = [(f"{a}_in_far", f"{a}_in_near") for a in ARMS]
    dests = [f"{a}_out_far" for a in ARMS]
    return RoadLayout(net, (f"{EGO_ARM}_in_far", f"{EGO_ARM}_in_near"), spawn, dests, None, w, inner)


def build_two_way(road: TwoWayRoad) -> RoadLayout:
    net = FastNetwork()
    w, n, m = road.lane_width, road.lanes, road.oncoming_lanes
    for k in range(n):
        net.add_lane(
            "fwd_a",
            "fwd_b",
            StraightLane([0, k * w], [road.length, k * w], w, _lines(k, n), speed_limit=road.speed_limit),
        )
    for k in range(m):
        # Oncoming lane k sits k+1 lanes to the ego's left; its own left side is the centre line,
        # already painted by the ego side's lane 0.
        y = -(k + 1) * w
        left = N if k == 0 else S
        net.add_lane(
            "onc_b",
            "onc_a",
            StraightLane([road.length, y], [0, y], w, (left, C if k == m - 1 else N), speed_limit=road.speed_limit),
        )
    inner = {(("fwd_a", "fwd_b", 0), 0), (("onc_b", "onc_a", 0), 0)}
    return RoadLayout(
        net, ("fwd_a", "fwd_b"), [("fwd_a", "fwd_b"), ("onc_b", "onc_a")], lane_width=w, inner_sides=inner
    )


def _to_highway(points: list[tuple[float, float]]) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    return np.stack([p[:, 0], -p[:, 1]], axis=1)


def build_route(road: RouteRoad) -> RoadLayout:
    """One edge whose lanes follow the given centerlines (polylines, our frame); with ``road.map``
    the drawn map and the drivable area are the map's."""
    net = FastNetwork()
    w, n = road.lane_width, len(road.lanes)
    for k, centerline in enumerate(road.lanes):
        lane = PolylineLane(_to_highway(centerline), width=w, line_types=_lines(k, n), speed_limit=road.speed_limit)
        net.add_lane("route_start", "route_end", lane)
    drawn, drivable = None, ()
    if road.map is not None:
        drivable = tuple(np.asarray(p, dtype=np.float64) for p in road.map.drivable_area)
        drawn = MapGeometry(
            lane_lines=tuple(
                LaneLine(points=np.asarray(ln.points, dtype=np.float64), kind=ln.kind) for ln in road.map.lane_lines
            ),
            road_edges=tuple(np.asarray(e, dtype=np.float64) for e in road.map.road_edges),
            drivable_area=drivable,
            lane_width=w,
        )
    edge = ("route_start", "route_end")
    return RoadLayout(net, edge, [edge], lane_width=w, map=drawn, drivable_area=drivable)


BUILDERS = {
    "highway": build_highway,
    "merge": build_merge,
    "roundabout": build_roundabout,
    "intersection": build_intersection,
    "two_way": build_two_way,
    "route": build_route,
}


def build_road(
    road: HighwayRoad | MergeRoad | RoundaboutRoad | IntersectionRoad | TwoWayRoad | RouteRoad,
    turn: str = "straight",
) -> RoadLayout:
    """Build the network of a scenario's road; ``turn`` picks the ego's exit at a junction."""
    layout = BUILDERS[road.type](road)
    if road.type == "roundabout":
        layout.ego_destination = f"{TURN_TARGET[turn]}_exit_far"
    elif road.type == "intersection":
        layout.ego_destination = f"{TURN_TARGET[turn]}_out_far"
    return layout
