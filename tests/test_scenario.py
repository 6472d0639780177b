import re
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


# Values at physical absurdity: each passed load (or crashed in numpy) though nothing a policy
# meets looks like it. The refusal names the file, the field and the value.
TINY_OR_HUGE = {
    "duration": ("duration: 4", "duration: 1.0e-300", "duration: 1e-300 s is shorter than one policy step"),
    "density": (
        "duration: 4",
        "duration: 4\ntraffic: {density: 1.0e-300}",
        "traffic.density: Input should be greater than or equal to 0.01, got 1e-300",
    ),
    "speed_limit": (
        "lanes: 3}",
        "lanes: 3, speed_limit: 1.0e-300}",
        "road.speed_limit: Input should be greater than or equal to 1, got 1e-300",
    ),
    "size": ("color: red", "color: red\n    size: [1.0e-300, 2.0, 2.0]", "objects.0.size: Value error, size must be"),
    "cut_in_duration": (
        "kind: lane_follow, lane: 0, start: 50, speed: 10",
        "kind: cut_in, from_lane: 0, to_lane: 1, speed: 9, time: 1, duration: 1.0e-300",
        "objects.0.track.duration: Input should be greater than or equal to 0.5, got 1e-300",
    ),
    "mix": (
        "duration: 4",
        "duration: 4\ntraffic: {mix: {car: 1.0e+308, truck: 1.0e+308}}",
        "traffic.mix: Value error, mix needs non-negative weights whose sum is finite and positive, got {'car': 1e+308",
    ),
    "ego_past_the_end": (
        "duration: 4",
        "duration: 4\nego: {lane: 1, longitudinal: 5000.0}",
        "ego.longitudinal: 5000.0 m is past the road's end; the highway road runs 2000 m along lane 1",
    ),
}


@pytest.mark.parametrize("case", sorted(TINY_OR_HUGE))
def test_physically_absurd_values_are_refused_naming_file_field_and_value(tmp_path, case):
    old, new, expected = TINY_OR_HUGE[case]
    assert old in GOOD
    p = tmp_path / f"{case}.yaml"
    p.write_text(GOOD.replace(old, new, 1))
    with pytest.raises(ScenarioError) as info:
        load_scenario(p)
    msg = str(info.value)
    assert msg.startswith(f"{p}: ") and expected in msg, msg


@pytest.mark.parametrize(
    "road, longitudinal, length",
    [
        ({"type": "roundabout"}, 151.0, "150"),
        ({"type": "merge"}, 1200.0, "1110"),
        ({"type": "intersection"}, 101.0, "100"),
    ],
)
def test_the_ego_starts_on_the_road_of_every_road_type(road, longitudinal, length):
    data = {"name": "t", "road": road, "ego": {"lane": 0, "longitudinal": longitudinal}}
    with pytest.raises(ScenarioError, match=rf"<dict>: ego\.longitudinal: {longitudinal!r} m .* runs {length} m"):
        scenario_from_dict(data)
    scenario_from_dict({**data, "ego": {"lane": 0, "longitudinal": float(length)}})  # at the end: on it


def test_text_fields_must_be_strings_not_bytes(tmp_path):
    p = tmp_path / "binary.yaml"
    p.write_text(GOOD.replace("name: tiny", "name: !!binary dGlueQ=="))  # b"tiny"
    with pytest.raises(ScenarioError, match=rf"^{p}: name: Input should be a valid string, got b'tiny'"):
        load_scenario(p)
    for field in ("prompt", "adapters", "objects.0.id", "objects.0.description", "objects.0.color"):
        data = scenario_from_dict(_yaml(GOOD)).model_dump(by_alias=True)
        cur = data
        *parents, last = field.split(".")
        for key in parents:
            cur = cur[int(key)] if key.isdigit() else cur[key]
        cur[last] = [b"x"] if last == "adapters" else b"red"
        with pytest.raises(ScenarioError, match=re.escape(f"<dict>: {field}")):
            scenario_from_dict(data)


def _yaml(text: str) -> dict:
    import yaml

    return yaml.safe_load(text)


def test_a_lane_placed_object_past_the_road_end_is_refused_where_the_road_is_built():
    from m4world_env.traffic.bridge import check_reset

    data = _yaml(GOOD)
    data["objects"][0]["track"]["start"] = 5000.0
    with pytest.raises(ScenarioError, match=r"objects\.box\.track: start: 5000\.0 m is past the road's end; .* 2000 m"):
        check_reset(scenario_from_dict(data), "t.yaml")


def test_randomized_scenarios_stay_within_the_bounds():
    """Draws scale density by up to 1.6 and count by up to 2: near the bounds they are kept inside."""
    data = _yaml(GOOD)
    data["traffic"] = {"count": 150, "density": 9.0}
    crowded = scenario_from_dict(data)
    data["traffic"] = {"count": 0, "density": 0.011}
    sparse = scenario_from_dict(data)
    for k in range(12):
        for s in (crowded, sparse):
            drawn = randomize_scenario(s, np.random.default_rng(k))
            scenario_from_dict(drawn.model_dump(by_alias=True))  # what the traffic bridge re-validates
