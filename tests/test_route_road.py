"""Route roads (lanes along polylines, scored along a route): geometry, loading, driving, drawing, scoring."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
from highway_env.road.lane import StraightLane

from m4world_env.evaluate import aggregate, format_table
from m4world_env.metrics import EpisodeMetrics
from m4world_env.scenario import ScenarioError, scenario_from_dict
from m4world_env.traffic.polyline import Polyline, PolylineLane, points_in_polygons
from world_model.scene import EgoState, MapGeometry, SceneFrame

RADIUS = 30.0


def quarter_turn(n: int = 60) -> list[tuple[float, float]]:
    """40 m straight along +x, a left quarter circle of ``RADIUS``, 60 m straight along +y."""
    arc = [(RADIUS * math.sin(t), RADIUS * (1 - math.cos(t))) for t in np.linspace(0, math.pi / 2, n)]
    return [(-40.0, 0.0), *arc, (RADIUS, RADIUS + 60.0)]


def route_scenario(**road: object) -> dict:
    return {
        "name": "route_test",
        "road": {
            "type": "route",
            "source": "ego_path",
            "lanes": [quarter_turn()],
            "reference_path": quarter_turn()[1:-1],
            "speed_limit": 8.0,
            **road,
        },
        "duration": 6.0,
        "ego": {"lane": 0, "longitudinal": 40.0, "speed": 8.0},
        "traffic": {"count": 0},
    }


def test_polyline_projects_onto_the_nearest_segment_and_extends_its_ends():
    line = Polyline.from_points([(0, 0), (10, 0), (10, 10), (10, 10)])  # the repeated vertex is dropped
    assert len(line.points) == 3 and line.length == pytest.approx(20.0)
    s, lateral = line.project(np.array([[4.0, 1.0], [11.0, 6.0], [-3.0, -2.0], [10.0, 14.0], [12.0, -1.0]]))
    assert s == pytest.approx([4.0, 16.0, -3.0, 24.0, 10.0])  # the last one: past the corner
    assert lateral == pytest.approx([1.0, -1.0, -2.0, 0.0, -1.0])  # left of the direction is positive
    assert line.position(16.0, 1.0) == pytest.approx([9.0, 6.0])
    assert float(line.heading(15.0)) == pytest.approx(math.pi / 2)
    shifted = line.offset(2.0)  # to the left: (0, 2) ... (8, 10)
    assert shifted.points[0] == pytest.approx([0.0, 2.0]) and shifted.points[-1] == pytest.approx([8.0, 10.0])
    with pytest.raises(ValueError, match="two distinct points"):
        Polyline.from_points([(1.0, 1.0), (1.0, 1.0)])


def test_polyline_lane_agrees_with_highway_envs_straight_lane():
    straight = StraightLane([0.0, 0.0], [50.0, 20.0], width=4.0)
    poly = PolylineLane([[0.0, 0.0], [25.0, 10.0], [50.0, 20.0]], width=4.0)
    assert poly.length == pytest.approx(straight.length)
    for p in ([10.0, 7.0], [30.0, 5.0], [-4.0, 1.0]):
        assert poly.local_coordinates(np.array(p)) == pytest.approx(straight.local_coordinates(np.array(p)))
    assert poly.position(12.0, 1.5) == pytest.approx(straight.position(12.0, 1.5))
    assert poly.heading_at(30.0) == pytest.approx(straight.heading_at(30.0))
    assert poly.on_lane(np.array([20.0, 8.0 + 1.0])) and not poly.on_lane(np.array([20.0, 8.0 + 6.0]))


def test_points_in_polygons_handles_concave_polygons():
    ell = np.array([(0, 0), (10, 0), (10, 2), (2, 2), (2, 10), (0, 10)], dtype=float)
    inside = points_in_polygons(np.array([[1, 1], [1, 9], [9, 1], [5, 5], [-1, 1]]), [ell])
    assert inside.tolist() == [True, True, True, False, False]


def test_a_degenerate_lane_is_refused_by_its_field():
    with pytest.raises(ScenarioError, match=r"road\.lanes\.0: Value error, a polyline needs at least two distinct"):
        scenario_from_dict(route_scenario(lanes=[[(1.0, 2.0), (1.0, 2.0)]]))
    with pytest.raises(ScenarioError, match=r"ego\.lane: lane 1 does not exist; the route road starts with 1 lane"):
        scenario_from_dict({**route_scenario(), "ego": {"lane": 1}})


def _ego_frame_pixel(bev_spec, ahead_m: float, left_m: float) -> tuple[int, int]:
    return int(bev_spec.forward_m - ahead_m), int(bev_spec.half_width_m - left_m)


def test_the_ego_drives_round_a_curved_lane_and_the_procedural_bev_draws_it():
    env = gym.make("M4World-v0", scenario=scenario_from_dict(route_scenario()), config={"observation_keys": ["bev"]})
    obs, info = env.reset(seed=0)
    assert info["road_source"] == "ego_path"
    spec = env.unwrapped.bev_spec
    bev = obs["bev"][..., 0]  # drivable area
    # The ego, 40 m into the lane, stands where the turn begins: the lane curves left ahead of it.
    on_curve = (RADIUS * math.sin(0.8), RADIUS * (1 - math.cos(0.8)))  # 21.5 m ahead, 9.1 m left
    assert bev[_ego_frame_pixel(spec, *on_curve)] == 1
    assert bev[_ego_frame_pixel(spec, on_curve[0], 0.0)] == 0  # straight ahead is off the road there
    from m4world_env import policies

    keep = policies.ConstantSpeedLaneKeeping()
    base = env.unwrapped
    for _ in range(30):
        obs, _, terminated, truncated, info = env.step(keep(base.bridge))
        if terminated or truncated:
            break
    m = info["episode_metrics"]
    assert m["off_road"] == 0.0 and m["off_route"] == 0.0 and m["route_deviation_max_m"] < 0.5
    assert m["route_progress"] == 1.0  # 48 m driven; the route (the quarter circle) is 47.1 m
    assert base.bridge.ego.yaw == pytest.approx(math.pi / 2, abs=0.05)  # round the turn, heading +y


def test_a_mapped_route_is_on_road_inside_its_drivable_area_only():
    square = [(-45.0, -5.0), (10.0, -5.0), (10.0, 5.0), (-45.0, 5.0)]
    drawn = {"drivable_area": [square], "lane_lines": [{"kind": "dashed", "points": [(-45.0, 2.0), (10.0, 2.0)]}]}
    s = scenario_from_dict(route_scenario(source="map_expansion", map=drawn))
    env = gym.make("M4World-v0", scenario=s, config={"observation_keys": ["state"]})
    _, info = env.reset(seed=0)
    bridge = env.unwrapped.bridge
    assert info["on_road"] and info["road_source"] == "map_expansion"
    assert len(bridge.map.drivable_area) == 1 and bridge.map.lane_lines[0].kind == "dashed"  # the map is drawn
    on_road = []
    for _ in range(30):
        _, _, terminated, truncated, info = env.step(np.array([0.0, 0.0], dtype=np.float32))
        on_road.append(info["on_road"])
        if terminated or truncated:
            break
    # Straight on past x = 10 m - half a car: the footprint leaves the map's drivable area.
    assert on_road[0] and not on_road[-1] and info["episode_metrics"]["off_road"] == 1.0


def _frame(x: float, y: float) -> SceneFrame:
    return SceneFrame(time=0.0, frame_index=0, ego=EgoState(x, y, 0.0, speed=5.0), objects=(), map=MapGeometry())


def test_route_progress_is_the_covered_fraction_of_the_route_ahead_of_the_start():
    route = Polyline.from_points([(0.0, 0.0), (10.0, 0.0), (10.0, 10.0)])
    m = EpisodeMetrics(dt=0.1, route=route)
    for x, y in [(0.0, 0.0), (5.0, 1.0), (10.5, 5.0)]:
        m.add_frame(_frame(x, y))
    out = m.summary()
    assert out["route_progress"] == pytest.approx(15.0 / 20.0) and out["progress"] == out["route_progress"]
    assert out["route_deviation_max_m"] == pytest.approx(1.0) and out["off_route"] == 0.0
    m.add_frame(_frame(16.0, 12.0))  # 6 m right of the second leg
    assert m.summary()["off_route"] == 1.0
    still = EpisodeMetrics(dt=0.1, route=Polyline.from_points([(0.0, 0.0), (0.1, 0.0)]))
    still.add_frame(_frame(0.0, 0.0))
    assert still.summary()["route_progress"] == 1.0  # a logged ego that stood still leaves nothing to cover


def test_eval_table_shows_off_route_for_route_scored_scenarios_only():
    base = {k: 0.0 for k in ("collision", "off_road", "progress", "ttc_violation", "comfort", "pdms")}
    base |= {"return": 0.0, "distance_m": 0.0}
    replay, plain = {**base, "off_route": 1.0, "route_deviation_max_m": 5.0}, dict(base)
    report = {"per_scenario": {"replay": aggregate([replay]), "highway": aggregate([plain])}}
    report["overall"] = aggregate([replay, plain])
    lines = format_table(report).splitlines()
    header = lines[0].split()
    col = header.index("off_route")
    assert lines[2].split()[col] == "1.000" and lines[3].split()[col] == "-"
    assert report["overall"]["off_route"] == 1.0  # over the episodes that have a route
