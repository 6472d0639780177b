"""The vectorized road (m4world_env.traffic.sim) must answer exactly as highway-env's Road."""

import numpy as np
import pytest
from highway_env.road.road import Road, RoadNetwork

from m4world_env.scenario import load_scenario
from m4world_env.traffic import TrafficBridge
from m4world_env.traffic.roads import build_road


@pytest.mark.parametrize("name", ["roundabout_fog", "intersection_pedestrian_night", "merge_cut_in"])
def test_closest_lane_matches_highway_env(name):
    net = build_road(load_scenario(name).road).network
    rng = np.random.default_rng(0)
    pos, head = rng.uniform(-150, 300, size=(200, 2)), rng.uniform(-4, 4, 200)
    fast = net.closest_lane_indices(pos, head)
    slow = [RoadNetwork.get_closest_lane_index(net, p, h) for p, h in zip(pos, head, strict=True)]
    assert fast == slow


@pytest.mark.parametrize("name", ["highway_dense_rain_dusk", "stopped_vehicle_snow", "roundabout_fog"])
def test_neighbours_match_highway_env(name):
    b = TrafficBridge(load_scenario(name))
    b.reset(seed=2)
    for _ in range(5):
        b.step([0.0, 0.0])
        road = b.road
        for v in road.vehicles:
            for lane in {v.lane_index, *road.network.side_lanes(v.lane_index)}:
                assert road.neighbour_vehicles(v, lane) == Road.neighbour_vehicles(road, v, lane)
