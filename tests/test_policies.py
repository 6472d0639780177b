import numpy as np
import pytest

from m4world_env.policies import (
    AutopilotConfig,
    ConstantSpeedLaneKeeping,
    IDMAutopilot,
    RandomPolicy,
    bridge_of,
)
from m4world_env.scenario import load_scenario
from m4world_env.traffic import TrafficBridge


@pytest.mark.parametrize("action_type", ["continuous", "discrete_meta"])
def test_autopilot_drives_dense_traffic_without_crashing(action_type):
    s = load_scenario("highway_dense_rain_dusk").model_copy(update={"duration": 12.0})
    b = TrafficBridge(s, action_type)
    b.reset(seed=1)
    pilot = IDMAutopilot(AutopilotConfig(random_lane_change_prob=0.05, random_speed_change_prob=0.05), seed=0)
    x0 = b.ego.x
    while not b.truncated:
        b.step(pilot({"bridge": b}))
        assert not b.crashed and b.on_road
    assert b.ego.x > x0 + 60.0  # dense traffic: it makes progress


def test_autopilot_follows_the_route_through_a_junction():
    s = load_scenario("intersection_pedestrian_night").model_copy(update={"objects": [], "duration": 14.0})
    b = TrafficBridge(s)
    b.reset(seed=0)
    pilot = IDMAutopilot()
    while not b.truncated and not b.crashed:
        b.step(pilot(b))
    assert b.lane_index[:2] == ("west_out_near", "west_out_far")  # the scenario's left turn
    assert b.ego.y > 20.0  # west is +y in our frame


def test_constant_speed_lane_keeping_holds_speed_and_lane():
    b = TrafficBridge(load_scenario("empty_highway"))
    b.reset(seed=0)
    b.ego_vehicle.position[1] += 0.8  # start 0.8 m off the lane centre
    policy = ConstantSpeedLaneKeeping(speed=25.0)
    for _ in range(40):
        b.step(policy(b))
    assert b.ego.speed == pytest.approx(25.0, abs=0.2) and abs(b.lane_offset) < 0.1 and b.lane_index[2] == 0
    meta = TrafficBridge(load_scenario("empty_highway"), "discrete_meta")
    meta.reset(seed=0)
    assert ConstantSpeedLaneKeeping()(meta) == 1


def test_random_policy_is_seeded_and_valid():
    b = TrafficBridge(load_scenario("empty_highway"))
    b.reset(seed=0)
    a1 = [RandomPolicy(seed=3)(b) for _ in range(1)] + [p(b) for p in [RandomPolicy(seed=3)]]
    assert np.array_equal(a1[0], a1[1]) and a1[0].dtype == np.float32 and np.all(np.abs(a1[0]) <= 1)
    m = TrafficBridge(load_scenario("empty_highway"), "discrete_meta")
    m.reset(seed=0)
    p = RandomPolicy(seed=0)
    acts = [p(m) for _ in range(50)]
    assert set(acts) == {0, 1, 2, 3, 4}
    for a in acts[:5]:
        m.step(a)


def test_bridge_of_rejects_other_inputs():
    class Env:
        bridge = TrafficBridge(load_scenario("empty_highway"))

    assert bridge_of(Env()) is Env.bridge
    with pytest.raises(TypeError, match="TrafficBridge"):
        bridge_of({"obs": 1})
