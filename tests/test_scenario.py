from pathlib import Path

import numpy as np
import pytest

from m4world_env.scenario import (
    SCENARIOS_DIR,
    Scenario,
    ScenarioError,
    list_scenarios,
    load_scenario,
    randomize_scenario,
    scenario_from_dict,
)
from world_model.scene import TIMES_OF_DAY, WEATHERS, ScenePrompt

GOOD = """
name: tiny
road: {type: highway, lanes: 3}
duration: 4
policy_frequency: 5
sensor_frequency: 10
weather: rain
time_of_day: night
objects:
  - id: box
    category: car
    color: red
    track: {kind: lane_follow, lane: 0, start: 50, speed: 10}
"""


def test_bundled_scenarios_cover_the_required_cases():
    names = list_scenarios()
    assert len(names) >= 8
    scenarios = [load_scenario(n) for n in names]
    assert {s.road.type for s in scenarios} >= {"highway", "merge", "roundabout", "intersection", "two_way"}
    assert {s.weather for s in scenarios} == set(WEATHERS)
    assert {s.time_of_day for s in scenarios} == set(TIMES_OF_DAY)
    assert any(s.traffic.count == 0 for s in scenarios)
    assert any(s.traffic.count >= 30 and s.traffic.density > 1 for s in scenarios)
    objects = [o for s in scenarios for o in s.objects]
    assert any(o.track.kind == "cut_in" for o in objects)
    assert any(o.category == "pedestrian" and o.track.kind == "waypoints" for o in objects)
    assert any(o.category == "car" and o.track.kind == "static" for o in objects)
    assert any(o.category == "tree_truck" for o in objects)
    assert (Path(__file__).parents[1] / "scenarios").resolve() == SCENARIOS_DIR.resolve()


def test_load_by_name_and_by_path_and_derived_values(tmp_path):
    by_name = load_scenario("merge_cut_in")
    assert load_scenario(SCENARIOS_DIR / "merge_cut_in.yaml") == by_name
    p = tmp_path / "tiny.yaml"
    p.write_text(GOOD)
    s = load_scenario(str(p))
    assert s.frames_per_step == 2 and s.num_steps == 20 and s.sim_dt == pytest.approx(0.1)
    assert s.prompt() == ScenePrompt(text="", weather="rain", time_of_day="night")
    fast = s.model_copy(update={"duration": 1.0})
    assert fast.num_steps == 5 and s.num_steps == 20


BAD_CASES = {
    "wrong_type": (
        GOOD.replace("speed: 10", "speed: fast"),
        "objects.0.track.speed: Input should be a valid number",
    ),
    "unknown_key": (
        GOOD.replace("duration: 4", "duration: 4\nlenght: 3"),
        "lenght: Extra inputs are not permitted",
    ),
    "bad_enum": (GOOD.replace("weather: rain", "weather: hail"), "weather: Input should be"),
    "bad_colour": (GOOD.replace("color: red", "color: mauve"), "objects.0.color"),
    "bad_rgb": (GOOD.replace("color: red", "color: [300, 0, 0]"), "objects.0.color"),
    "missing_field": (GOOD.replace("name: tiny\n", ""), "name: Field required"),
    "bad_road": (GOOD.replace("type: highway", "type: canal"), "road: Input tag 'canal'"),
    "bad_track": (
        GOOD.replace("kind: lane_follow, lane: 0, start: 50, speed: 10", "kind: static"),
        "objects.0.track",
    ),
    "infinite": (GOOD.replace("speed: 10", "speed: .inf"), "objects.0.track.speed: Input should be a finite number"),
    "ratio": (GOOD.replace("policy_frequency: 5", "policy_frequency: 3"), "integer"),
    "ego_lane_out_of_range": (
        GOOD.replace("duration: 4", "duration: 4\nego: {lane: 3}"),
        "ego.lane: lane 3 does not exist; the highway road starts with 3 lanes",
    ),
    "object_lane_out_of_range": (
        GOOD.replace("lane: 0, start: 50", "lane: 7, start: 50"),
        "objects.0.track.lane: lane 7 does not exist",
    ),
    "cut_in_lane_out_of_range": (
        GOOD.replace("road: {type: highway, lanes: 3}", "road: {type: roundabout}\nego: {lane: 0}").replace(
            "kind: lane_follow, lane: 0, start: 50, speed: 10",
            "kind: cut_in, from_lane: 0, to_lane: 1, speed: 9, time: 1",
        ),
        "objects.0.track.to_lane: lane 1 does not exist; the roundabout road starts with 1 lane (0 = leftmost)",
    ),
    "yaml_syntax": (
        GOOD.replace("road: {type: highway, lanes: 3}", "road: {type: highway, lanes: 3"),
        "YAML syntax error at line",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_malformed_scenarios_name_file_and_field(tmp_path, case):
    text, expected = BAD_CASES[case]
    p = tmp_path / f"{case}.yaml"
    p.write_text(text)
    with pytest.raises(ScenarioError) as info:
        load_scenario(p)
    msg = str(info.value)
    assert msg.startswith(str(p)), msg
    assert expected in msg, msg
    assert "Traceback" not in msg


def test_unknown_scenario_name_lists_bundled():
    with pytest.raises(ScenarioError, match="highway_sunny_day"):
        load_scenario("no_such_scenario")
    assert issubclass(ScenarioError, ValueError)


def test_randomize_is_seeded_and_varies():
    s = load_scenario("highway_sunny_day")
    a = randomize_scenario(s, np.random.default_rng(3))
    b = randomize_scenario(s, np.random.default_rng(3))
    assert a == b and isinstance(a, Scenario)
    many = [randomize_scenario(s, np.random.default_rng(k)) for k in range(12)]
    assert len({m.weather for m in many}) > 1 and len({m.time_of_day for m in many}) > 1
    assert len({m.traffic.count for m in many}) > 1
    assert all(m.road == s.road and m.objects == s.objects for m in many)


@pytest.mark.parametrize("road", ["highway", "merge", "roundabout", "intersection", "two_way"])
def test_start_lanes_match_the_built_network(road):
    """The load-time lane check counts lanes as the road builder lays them out."""
    from m4world_env.traffic.roads import build_road

    spec = scenario_from_dict({"name": "t", "road": {"type": road}, "ego": {"lane": 0}}).road
    layout = build_road(spec)
    frm, to = layout.ego_edge
    assert spec.start_lanes == len(layout.network.graph[frm][to])


def test_scenarios_check_cli_lists_good_files_and_refuses_bad_ones(tmp_path, capsys):
    from m4world_env.cli import main

    good, bad = tmp_path / "good.yaml", tmp_path / "bad.yaml"
    good.write_text(GOOD)
    bad.write_text(GOOD.replace("lane: 0, start: 50", "lane: 5, start: 50"))
    assert main(["scenarios", "--check", str(good)]) == 0
    assert "tiny" in capsys.readouterr().out
    assert main(["scenarios", "--check", str(bad)]) == 2
    assert f"{bad}: objects.0.track.lane: lane 5 does not exist" in capsys.readouterr().err
