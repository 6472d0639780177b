import math

import numpy as np
import pytest

from m4world_env.scenario import ScenarioError, list_scenarios, load_scenario, scenario_from_dict
from m4world_env.traffic import ActionError, TrafficBridge, UnknownObjectError
from world_model.scene import CATEGORIES, SceneFrame


def _quiet_highway(**updates):
    base = {
        "name": "quiet",
        "road": {"type": "highway", "lanes": 3, "length": 1000},
        "duration": 10,
        "ego": {"lane": 1, "longitudinal": 50, "speed": 20},
        "traffic": {"count": 0},
    }
    base.update(updates)
    return scenario_from_dict(base)


@pytest.mark.parametrize("name", list_scenarios())
def test_every_scenario_runs_its_full_duration(name):
    """Through the scripted events (cut-ins, stopped vehicles, crossings), with either action type."""
    s = load_scenario(name)
    for action_type, action in (("continuous", [0.0, 0.0]), ("discrete_meta", 1)):
        b = TrafficBridge(s, action_type)
        f0 = b.reset(seed=0)
        assert isinstance(f0, SceneFrame) and f0.frame_index == 0 and f0.scenario == name
        n = 0
        while not b.truncated:
            frames = b.step(action)
            assert len(frames) == s.frames_per_step and all(f.map is f0.map for f in frames)
            n += 1
        if b.end_of_road:  # the ego ran out of road first (roundabout_fog's 150 m exit): still on it
            assert n < s.num_steps and b.on_road and not b.crashed
        else:
            assert n == s.num_steps and b.time == pytest.approx(s.duration)
        for o in frames[-1].objects:
            assert o.box.center[2] == pytest.approx(o.box.size[2] / 2)


def test_one_scenario_runs_its_full_duration():
    s = load_scenario("empty_highway")
    b = TrafficBridge(s)
    b.reset(seed=0)
    frames = []
    for _ in range(s.num_steps):
        assert not b.truncated
        frames += b.step([0.0, 0.0])
    assert b.truncated and b.time == pytest.approx(s.duration)
    assert len(frames) == s.num_steps * s.frames_per_step
    assert [f.frame_index for f in frames] == list(range(1, len(frames) + 1))


def _rollout(seed, steps=6):
    b = TrafficBridge(load_scenario("highway_sunny_day"))
    frames = [b.reset(seed=seed)]
    for _ in range(steps):
        frames += b.step([0.1, 0.0])
    return [f.to_dict(include_static=False) for f in frames]


def test_same_seed_same_frames_different_seed_different_traffic():
    a, b, c = _rollout(7), _rollout(7), _rollout(8)
    assert a == b
    assert [o["box"] for o in a[0]["objects"]] != [o["box"] for o in c[0]["objects"]]


def test_frame_conversion_forward_and_left():
    s = _quiet_highway(
        objects=[{"id": "left_car", "category": "car", "track": {"kind": "static", "lane": 0, "longitudinal": 80}}]
    )
    b = TrafficBridge(s, "discrete_meta")
    f0 = b.reset(seed=0)
    assert f0.objects[0].box.center[1] > f0.ego.y  # lane 0 is to the ego's left
    assert f0.ego.yaw == pytest.approx(0.0) and f0.ego.y == pytest.approx(-4.0)
    xs = [f.ego.x for f in b.step(1)]
    assert xs[0] > f0.ego.x and xs[1] > xs[0]
    b.remove_object("left_car")
    b.step(0)  # LANE_LEFT
    for _ in range(10):
        frames = b.step(1)
    assert frames[-1].ego.y == pytest.approx(0.0, abs=0.3) and b.lane_index[2] == 0
    b.step(2)  # LANE_RIGHT
    for _ in range(10):
        frames = b.step(1)
    assert frames[-1].ego.y == pytest.approx(-4.0, abs=0.3) and b.lane_index[2] == 1


def test_continuous_acceleration_mapping():
    s = _quiet_highway()
    b = TrafficBridge(s)
    b.reset(seed=0)
    step_dt = s.frames_per_step / s.sensor_frequency
    b.step([1.0, 0.0])
    assert b.ego.speed == pytest.approx(20.0 + 5.0 * step_dt)
    b.step([-0.5, 0.0])
    assert b.ego.speed == pytest.approx(20.0 + 5.0 * step_dt - 2.5 * step_dt)
    y0 = b.ego.y
    b.step([0.0, 0.5])  # highway-env convention: positive steering turns right
    assert b.ego.steering == pytest.approx(-math.pi / 8)  # reported counter-clockwise positive
    b.step([0.0, 0.0])
    assert b.ego.y < y0


def test_discrete_meta_speed_actions():
    b = TrafficBridge(_quiet_highway(), "discrete_meta")
    b.reset(seed=0)
    start = b.ego_vehicle.target_speed
    b.step(3)  # FASTER
    assert b.ego_vehicle.target_speed > start
    for _ in range(3):
        b.step(4)  # SLOWER
    assert b.ego_vehicle.target_speed < start
    for _ in range(15):
        b.step(1)
    assert b.ego.speed < 20.0


@pytest.mark.parametrize(
    "action_type,action",
    [
        ("continuous", [0.0]),
        ("continuous", [0.0, 0.0, 0.0]),
        ("continuous", [np.nan, 0.0]),
        ("continuous", [1.5, 0.0]),
        ("continuous", "fast"),
        ("discrete_meta", 5),
        ("discrete_meta", 1.0),
        ("discrete_meta", True),
        ("discrete_meta", -1),
    ],
)
def test_bad_actions_raise_action_error(action_type, action):
    b = TrafficBridge(_quiet_highway(), action_type)
    b.reset(seed=0)
    with pytest.raises(ActionError):
        b.step(action)
    with pytest.raises(ActionError):
        TrafficBridge(_quiet_highway(), "joystick")


def _track(frames, track_id):
    return [next(o for o in f.objects if o.track_id == track_id) for f in frames]


def test_cut_in_happens_at_time_t():
    s = load_scenario("merge_cut_in").model_copy(update={"duration": 8.0})
    tr = s.objects[0].track
    b = TrafficBridge(s)
    frames = [b.reset(seed=0)]
    while not b.truncated:
        frames += b.step([0.0, 0.0])
    ys = {round(f.time, 3): o.box.center[1] for f, o in zip(frames, _track(frames, "cutting_van"), strict=True)}
    before = [y for t, y in ys.items() if t <= tr.time]
    after = [y for t, y in ys.items() if t >= tr.time + tr.duration]
    assert np.allclose(before, 0.0) and np.allclose(after, -4.0)
    during = [y for t, y in ys.items() if tr.time < t < tr.time + tr.duration]
    assert all(-4.0 < y < 0.0 for y in during)


def test_pedestrian_crosses_the_road():
    s = load_scenario("intersection_pedestrian_night")
    s = s.model_copy(update={"traffic": {"count": 0}, "duration": 12.0, "ego": {"speed": 0.0, "lane": 0}})
    b = TrafficBridge(s)
    frames = [b.reset(seed=0)]
    while not b.truncated:
        frames += b.step([0.0, 0.0])  # the ego waits before the crossing
    walker = _track(frames, "walker")
    assert walker[0].box.center[1] == pytest.approx(-7.0) and walker[-1].box.center[1] == pytest.approx(7.0)
    mid = next(o for f, o in zip(frames, walker, strict=True) if f.time == pytest.approx(6.5))
    assert mid.box.center[1] == pytest.approx(0.0) and mid.velocity[1] > 1.0


def test_static_objects_are_where_the_scenario_says():
    b = TrafficBridge(load_scenario("stopped_vehicle_snow"))
    f0 = b.reset(seed=0)
    objs = {o.track_id: o for o in f0.objects}
    car = objs["broken_car"]
    assert car.box.center == pytest.approx((250.0, -4.0, car.box.size[2] / 2))
    assert objs["barrier"].box.center[:2] == pytest.approx((244.0, -4.0))
    assert objs["cone_1"].box.center[1] == pytest.approx(-3.0)  # 1 m left of lane 1's centre
    assert car.color_name == "red" and car.description.startswith("a red hatchback")


def test_ego_crashes_into_stopped_vehicle_and_idm_brakes_for_it():
    s = load_scenario("stopped_vehicle_snow").model_copy(update={"traffic": {"count": 0}})
    b = TrafficBridge(s)
    b.reset(seed=0)
    while not b.crashed and not b.truncated:
        b.step([0.0, 0.0])
    assert b.crashed and b.ego.x < 250.0
    follower = {
        "id": "follower",
        "category": "van",
        "track": {"kind": "lane_follow", "lane": 1, "start": 120, "speed": 20, "mode": "idm"},
    }
    s2 = s.model_copy(
        update={
            "objects": [
                *s.objects,
                scenario_from_dict({"name": "x", "road": {"type": "highway"}, "objects": [follower]}).objects[0],
            ],
            "ego": s.ego.model_copy(update={"lane": 0}),
        }
    )
    b2 = TrafficBridge(s2)
    b2.reset(seed=0)
    for _ in range(60):
        b2.step([0.0, 0.0])
    van = b2._get("follower")
    assert not van.crashed and van.speed < 0.5 and van.position[0] < 250.0 - 4.0


def test_insert_edit_remove_objects():
    b = TrafficBridge(_quiet_highway())
    b.reset(seed=0)
    for k, cat in enumerate(CATEGORIES):
        b.insert_object({"id": f"o{k}", "category": cat, "track": {"kind": "static", "x": 100.0 + 10 * k, "y": 8.0}})
    frame = b.step([0.0, 0.0])[-1]
    assert {o.category for o in frame.objects} == set(CATEGORIES)
    with pytest.raises(ScenarioError, match="insert_object: track.speed"):
        b.insert_object({"id": "bad", "category": "car", "track": {"kind": "lane_follow", "lane": 0, "speed": "x"}})
    with pytest.raises(ScenarioError, match="already in use"):
        b.insert_object({"id": "o0", "category": "car", "track": {"kind": "static", "x": 0.0, "y": 0.0}})
    b.edit_object("o0", category="bus", color="yellow")
    bus = next(o for o in b.step([0.0, 0.0])[-1].objects if o.track_id == "o0")
    assert bus.category == "bus" and bus.color_name == "yellow" and "yellow" in bus.description
    assert bus.box.size[0] == pytest.approx(11.5)
    b.edit_object("o1", track={"kind": "lane_follow", "lane": 0, "start": 200, "speed": 10})
    xs = [next(o for o in f.objects if o.track_id == "o1").box.center[0] for f in b.step([0.0, 0.0])]
    assert xs[1] > xs[0] > 200.0
    with pytest.raises(ValueError, match="editable"):
        b.edit_object("o2", wings=2)
    b.remove_object("o0")
    assert "o0" not in {o.track_id for o in b.step([0.0, 0.0])[-1].objects}
    with pytest.raises(UnknownObjectError):
        b.remove_object("o0")


def test_map_geometry_and_state():
    b = TrafficBridge(load_scenario("highway_sunny_day"))
    f0 = b.reset(seed=0)
    m = b.map
    assert m is f0.map and len(m.drivable_area) == 4 and len(m.road_edges) == 2
    kinds = [ln.kind for ln in m.lane_lines]
    assert kinds.count("solid") == 2 and kinds.count("dashed") == 3
    assert sorted(e[0, 1] for e in m.road_edges) == pytest.approx([-14.0, 2.0])
    round_map = TrafficBridge(load_scenario("roundabout_fog")).reset(seed=0).map
    ring = np.concatenate(round_map.drivable_area)
    assert np.hypot(ring[:, 0], ring[:, 1]).min() == pytest.approx(18.0, abs=0.1)
    feats = b.state_features(5)
    assert feats.shape == (6, 7) and feats[0, 0] == 1 and feats[0, 1] == pytest.approx(f0.ego.x)
    dists = np.hypot(feats[1:, 1], feats[1:, 2])[feats[1:, 0] > 0]
    assert np.all(np.diff(dists) >= 0)
    assert b.num_lanes == 4 and b.on_road and not b.crashed and abs(b.lane_offset) < 1e-9
    assert math.isfinite(b.ego.yaw_rate)


def test_vectorized_separation_never_skips_a_pair_highway_env_would_collide():
    from highway_env import utils

    from m4world_env.traffic.sim import swept_apart

    rng = np.random.default_rng(0)
    n = 400
    pos = rng.uniform(-6, 6, (n, 2))
    head = rng.uniform(-np.pi, np.pi, n)
    half = np.stack([rng.uniform(0.5, 6, n), rng.uniform(0.3, 1.5, n)], -1)
    disp = rng.normal(0, 1.5, (n, 2))
    ii, jj = np.arange(0, n, 2), np.arange(1, n, 2)
    apart = swept_apart(pos, head, half, disp, ii, jj)

    def polygon(k):
        c, s = np.cos(head[k]), np.sin(head[k])
        local = np.array([[-1, -1], [-1, 1], [1, 1], [1, -1], [-1, -1]]) * half[k]
        return local @ np.array([[c, s], [-s, c]]) + pos[k]

    pairs = zip(ii, jj, strict=True)
    will = np.array([utils.are_polygons_intersecting(polygon(i), polygon(j), disp[i], disp[j])[1] for i, j in pairs])
    assert not (apart & will).any()  # never skips a collision
    assert (apart == ~will).mean() > 0.97  # and skips nearly every pair that is apart
    assert apart.any() and will.any()


def test_a_refused_edit_changes_nothing():
    b = TrafficBridge(load_scenario("highway_sunny_day"))
    frame = b.reset(seed=0)
    car = next(o for o in frame.objects if o.track_id.startswith("idm_"))
    for speed in (-5, "fast", float("nan")):
        with pytest.raises(ValueError, match="speed"):
            b.edit_object(car.track_id, color="green", speed=speed)
    after = next(o for o in b.step([0.0, 0.0])[-1].objects if o.track_id == car.track_id)
    assert after.color_name == car.color_name and after.description == car.description
    b.edit_object(car.track_id, color="green", speed=5)
    after = next(o for o in b.step([0.0, 0.0])[-1].objects if o.track_id == car.track_id)
    assert after.color_name == "green"
