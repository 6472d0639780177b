"""nuScenes import through the real devkit, on a miniature dataset written by the test."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("nuscenes")

from m4world_env.cli import main  # noqa: E402
from tests import nuscenes_mini as mini  # noqa: E402
from world_model.data import list_clips, read_clip  # noqa: E402
from world_model.data.nuscenes_import import map_category  # noqa: E402
from world_model.sensors import LidarSpec  # noqa: E402


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    root = mini.write_mini_nuscenes(tmp_path_factory.mktemp("nuscenes"))
    out = tmp_path_factory.mktemp("clips")
    rc = main(["import", "nuscenes", "--dataroot", str(root), "--version", mini.VERSION, "--out", str(out)])
    assert rc == 0
    return root, out


def test_every_scene_becomes_a_10hz_clip(imported):
    _, out = imported
    clip = read_clip(out, "nuscenes_scene-0001")
    assert clip.fps == pytest.approx(10.0)
    assert clip.num_frames == 11  # 1 s between the first and last 2 Hz keyframe
    assert clip.cameras.shape == (11, 6, 64, 112, 3)
    assert clip.lidar.shape == (11, 32, 1024)
    assert clip.frames[0].prompt.text == "Wait at light, peds crossing"
    assert read_clip(out, "nuscenes_scene-0002").frames[0].prompt.text.startswith("Night, rain")


def test_box_lands_at_the_known_pixel_of_the_front_camera(imported):
    _, out = imported
    clip = read_clip(out, "nuscenes_scene-0001")
    frame = clip.frames[0]
    cam = frame.rig.cameras[frame.rig.names.index("FRONT")]
    car = next(o for o in frame.objects if o.category == "car")
    p = frame.world_to_lidar(np.asarray(car.box.center))
    pc = (p - cam.t) @ cam.R
    u = cam.K[0, 0] * pc[0] / pc[2] + cam.K[0, 2]
    v = cam.K[1, 1] * pc[1] / pc[2] + cam.K[1, 2]
    u0, v0 = mini.car_pixel_original()
    sx, sy = 112 / mini.IMAGE_W, 64 / mini.IMAGE_H
    assert u == pytest.approx((u0 + 0.5) * sx - 0.5, abs=1e-6)
    assert v == pytest.approx((v0 + 0.5) * sy - 0.5, abs=1e-6)
    # The white square painted there in the original JPEG is there in the resized view.
    img = clip.cameras[0, frame.rig.names.index("FRONT")].mean(axis=-1)
    assert img[round(v), round(u)] > 200
    assert img[5, 5] < 60
    # The size and yaw survive (nuScenes w, l, h -> our l, w, h; heading along the ego's).
    assert car.box.size == pytest.approx((4.5, 1.9, 1.6))
    assert car.box.yaw == pytest.approx(frame.ego.yaw)
    assert car.box.center[2] == pytest.approx(mini.CAR_IN_EGO[2])


def test_boxes_between_keyframes_are_interpolated(imported):
    _, out = imported
    frames = read_clip(out, "nuscenes_scene-0001").frames
    for fr in frames:  # the car keeps pace with the ego: 20 m ahead at every 10 Hz frame
        car = next(o for o in fr.objects if o.category == "car")
        ahead = fr.world_to_lidar(np.asarray(car.box.center))
        assert ahead[0] == pytest.approx(mini.CAR_IN_EGO[0] - mini.LIDAR_IN_EGO[0], abs=1e-6)
        assert ahead[1] == pytest.approx(mini.CAR_IN_EGO[1], abs=1e-6)


def test_lidar_point_lands_in_the_known_range_map_cell(imported):
    _, out = imported
    clip = read_clip(out, "nuscenes_scene-0001")
    col = LidarSpec().azimuth // 4  # azimuth +90 deg: straight left
    assert clip.lidar[0, mini.POINT_ROW, col] == pytest.approx(mini.POINT_RANGE, abs=0.01)
    assert np.count_nonzero(clip.lidar[0, :, : LidarSpec().azimuth // 2]) == 1  # nothing else on the left
    assert clip.frames[0].lidar.mount_height == pytest.approx(mini.LIDAR_IN_EGO[2])


def test_categories_map_with_a_fallback(imported):
    _, out = imported
    cats = sorted(o.category for o in read_clip(out, "nuscenes_scene-0001").frames[0].objects)
    assert cats == ["barrier", "car"]  # the animal falls back to a static obstacle
    assert map_category("vehicle.bicycle") == "cyclist"
    assert map_category("human.pedestrian.adult") == "pedestrian"


def test_bev_is_the_corridor_along_the_ego_path(imported):
    _, out = imported
    clip = read_clip(out, "nuscenes_scene-0001")
    assert clip.meta["bev_from"] == "ego_path"
    h, w, _ = clip.bev.shape[1:]
    assert clip.bev[0, h // 2, w // 2, 0] == 1  # the ego stands on drivable area
    assert clip.bev[0, h // 2, 0, 0] == 0  # 40 m to the side is not


def test_bev_comes_from_the_map_expansion_where_present(imported):
    _, out = imported
    clip = read_clip(out, "nuscenes_scene-0002")
    assert clip.meta["bev_from"] == "map_expansion"
    bev = clip.bev[0]
    spec = clip.frames[0].bev
    h = bev.shape[0]

    def column(left_m: float) -> int:  # BevSpec: column 0 is the far left
        return int(spec.half_width_m - left_m)  # m_per_px = 1

    assert bev[h // 2, column(0.5), 0] == 1  # the ego on drivable area
    assert bev[h // 2, column(15.5), 0] == 0  # 15 m left: past the drivable rectangle's edge (x = 90)
    divider = bev[h // 2, :, 1]
    assert divider[column(2.0) - 1 : column(2.0) + 1].any()  # the lane divider 2 m left
    assert divider[column(-6.0) - 1 : column(-6.0) + 1].any()  # the road divider 6 m right
    assert divider.sum() <= 6  # and nothing else on that row
    road_edge = bev[h // 2, :, 2]
    assert road_edge[column(10.0) - 1 : column(10.0) + 1].any()  # the drivable area's outline at x = 90


def test_imported_clips_train_mixed_with_procedural_ones(imported, tmp_path):
    from tests.model_fixtures import train_cli

    root, _ = imported
    data = tmp_path / "mixed"
    assert (
        main(["record", "--scenario", "highway_sunny_day", "--duration", "0.3", "--preset", "tiny", "--out", str(data)])
        == 0
    )
    assert (
        main(
            [
                "import",
                "nuscenes",
                "--dataroot",
                str(root),
                "--scenes",
                "scene-0002",
                "--preset",
                "tiny",
                "--out",
                str(data),
            ]
        )
        == 0
    )
    summary = train_cli("--stage", "vae", "--data", str(data), "--run", str(tmp_path / "run"), "--steps", "2")
    assert summary


@pytest.mark.parametrize(
    "change, args, message",
    [
        (None, ["--dataroot", "/nonexistent/nuscenes"], "--dataroot /nonexistent/nuscenes does not exist"),
        (None, ["--version", "v1.0-trainval"], "--version 'v1.0-trainval' is not in"),
        (None, ["--scenes", "scene-9999"], "--scenes ['scene-9999'] not in v1.0-mini"),
        ("samples/CAM_FRONT/scene-0002__CAM_FRONT__1.jpg", [], "scene scene-0002: cannot read camera file"),
        ("samples/LIDAR_TOP/scene-0001__LIDAR_TOP__0.pcd.bin", [], "scene scene-0001: cannot read LiDAR file"),
    ],
)
def test_bad_input_is_refused_by_name(tmp_path, capsys, change, args, message):
    root = mini.write_mini_nuscenes(tmp_path / "ns")
    if change:
        (root / change).write_bytes(b"\x00\x01garbage")
    out = tmp_path / "out"
    cmd = ["import", "nuscenes", "--dataroot", str(root), "--out", str(out), *args]
    assert main(cmd) == 2
    err = capsys.readouterr().err
    assert message in err
    if change:
        assert change in err
        # A sensor file is read while its scene is converted: the scenes before it are whole clips,
        # the refused scene has none, not even a partial one.
        before = ["nuscenes_scene-0001"] if "scene-0002" in change else []
        assert (list_clips(out) if out.exists() else []) == before
        assert sorted(p.name for p in out.glob("*") if p.is_dir()) == before


def _first_lidar_cs(rows):
    return next(r for r in rows if r["token"] == mini.token("cs", "LIDAR_TOP"))


def _row(rows, token):
    return next(r for r in rows if r["token"] == token)


def _set(token, field, value):
    return lambda rows: _row(rows, token).__setitem__(field, value)


NAN = float("nan")
SAMPLE_1 = mini.token("sample", 0, 1)
LIDAR_SD_1 = mini.token("sd", 0, "LIDAR_TOP", 1)
EGO_0 = mini.token("ego", 0, "LIDAR_TOP", 0)
CAR_ANN_0 = mini.token("ann", 0, "car", 0)
CS_FRONT = mini.token("cs", "CAM_FRONT")
K_ZERO = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
K_NAN = [[NAN, 0.0, 80.0], [0.0, 126.0, 45.0], [0.0, 0.0, 1.0]]


def _reverse_sample_1(rows):
    _row(rows, SAMPLE_1)["timestamp"] = _row(rows, mini.token("sample", 0, 0))["timestamp"] - 1


def _no_front_key_frame(rows):
    _row(rows, mini.token("sd", 0, "CAM_BACK", 0))["is_key_frame"] = False


def _lidar_loop(rows):  # the second sweep leads back to the first
    _row(rows, LIDAR_SD_1)["next"] = mini.token("sd", 0, "LIDAR_TOP", 0)


def _duplicate_scene_name(rows):
    rows[1]["name"] = rows[0]["name"]


# (table, edit, what the one error line names: the table file, the row, the field, the value)
MALFORMED_TABLES = {
    "table is an object": ("scene", lambda rows: {"rows": rows}, ["a table is a JSON list", "got an object"]),
    "row is null": ("sample", lambda rows: [None, *rows[1:]], ["row #0 is None"]),
    "scene without name": (
        "scene",
        lambda rows: [{k: v for k, v in rows[0].items() if k != "name"}, *rows[1:]],
        [f"row {mini.token('scene', 0)!r}", "field 'name' is missing"],
    ),
    "dangling first_sample_token": (
        "scene",
        _set(mini.token("scene", 0), "first_sample_token", "nope"),
        ["field 'first_sample_token' is 'nope'", "sample.json"],
    ),
    "dangling ego_pose_token": (
        "sample_data",
        _set(LIDAR_SD_1, "ego_pose_token", "nope"),
        [repr(LIDAR_SD_1), "field 'ego_pose_token' is 'nope'", "ego_pose.json"],
    ),
    "string translation": ("ego_pose", _set(EGO_0, "translation", "1,2,3"), [repr(EGO_0), "'translation' is '1,2,3'"]),
    "reversed timestamps": ("sample", _reverse_sample_1, [repr(SAMPLE_1), "field 'timestamp'", "strictly increase"]),
    "NaN timestamp": ("sample", _set(SAMPLE_1, "timestamp", NAN), [repr(SAMPLE_1), "field 'timestamp' is nan"]),
    "zero ego quaternion": ("ego_pose", _set(EGO_0, "rotation", [0, 0, 0, 0]), ["'rotation' is [0, 0, 0, 0]", "unit"]),
    "zero LiDAR calibration rotation": (
        "calibrated_sensor",
        lambda rows: _first_lidar_cs(rows).__setitem__("rotation", [0, 0, 0, 0]),
        [repr(mini.token("cs", "LIDAR_TOP")), "field 'rotation' is [0, 0, 0, 0]"],
    ),
    "zero intrinsics": ("calibrated_sensor", _set(CS_FRONT, "camera_intrinsic", K_ZERO), [repr(CS_FRONT), "> 0"]),
    "NaN intrinsics": ("calibrated_sensor", _set(CS_FRONT, "camera_intrinsic", K_NAN), ["'camera_intrinsic' is [[nan"]),
    "negative size": ("sample_annotation", _set(CAR_ANN_0, "size", [-1.9, 4.5, 1.6]), ["'size' is [-1.9, 4.5, 1.6]"]),
    "NaN annotation pose": (
        "sample_annotation",
        _set(CAR_ANN_0, "translation", [NAN, 0.0, 0.0]),
        [repr(CAR_ANN_0), "field 'translation' is [nan, 0.0, 0.0]"],
    ),
    "no camera keyframe": (
        "sample_data",
        _no_front_key_frame,
        ["no CAM_BACK keyframe", repr(mini.token("sample", 0, 0))],
    ),
    "camera without pixels": (
        "sample_data",
        _set(mini.token("sd", 0, "CAM_FRONT", 0), "width", 0),
        ["field 'width' is 0"],
    ),
    "missing sensor file": (
        "sample_data",
        _set(LIDAR_SD_1, "filename", "sweeps/LIDAR_TOP/gone.pcd.bin"),
        [repr(LIDAR_SD_1), "field 'filename' is 'sweeps/LIDAR_TOP/gone.pcd.bin'", "no such file"],
    ),
    "looping chain": ("sample_data", _lidar_loop, ["field 'timestamp'", "strictly increase"]),
    "two scenes of one name": ("scene", _duplicate_scene_name, ["field 'name' is 'scene-0001'"]),
}


@pytest.mark.parametrize("case", sorted(MALFORMED_TABLES))
def test_malformed_tables_are_refused_by_table_row_and_field_before_any_clip(tmp_path, capsys, case):
    table, edit, names = MALFORMED_TABLES[case]
    root = mini.write_mini_nuscenes(tmp_path / "ns")
    mini.edit_table(root, table, edit)
    out = tmp_path / "out"
    assert main(["import", "nuscenes", "--dataroot", str(root), "--out", str(out), "--preset", "tiny"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("m4world import: error: ")  # one line, no traceback
    assert f"{root / mini.VERSION / table}.json: " in err
    for name in names:
        assert name in err
    assert not out.exists()  # nothing written, the other scene's clip included


def test_a_scene_is_checked_whole_before_any_clip_is_written(tmp_path, capsys):
    root = mini.write_mini_nuscenes(tmp_path / "ns")
    later = mini.token("sd", 1, "LIDAR_TOP", 3)  # scene-0002's last sweep, timed before the one before it
    mini.edit_table(root, "sample_data", _set(later, "timestamp", 0))
    out = tmp_path / "out"
    assert main(["import", "nuscenes", "--dataroot", str(root), "--out", str(out), "--preset", "tiny"]) == 2
    assert f"row {later!r}: field 'timestamp' is 0" in capsys.readouterr().err
    assert not out.exists()  # scene-0001 comes first and is fine, yet no clip of it either
    # A scene's chains are checked when it is chosen: the other scene alone imports.
    args = ["--scenes", "scene-0001", "--preset", "tiny"]
    assert main(["import", "nuscenes", "--dataroot", str(root), "--out", str(out), *args]) == 0
    assert list_clips(out) == ["nuscenes_scene-0001"]


def _node_nan(layers):
    layers["node"][0]["x"] = NAN


def _zero_radius(layers):
    layers["arcline_path_3"]["turn_left"][0]["radius"] = 0.0


def _dangling_polygon(layers):
    layers["drivable_area"][0]["polygon_tokens"] = ["p0", "nope"]


def _arclines_as_list(layers):
    layers["arcline_path_3"] = list(layers["arcline_path_3"].values())


@pytest.mark.parametrize(
    "edit, names",
    [
        (_node_nan, ["layer 'node': row 'n0'", "field 'x' is nan"]),
        (_zero_radius, ["layer 'arcline_path_3' lane 'turn_left'", "field 'radius' is 0.0"]),
        (_dangling_polygon, ["layer 'drivable_area': row 'da0'", "field 'polygon_tokens'", "'nope' is no token"]),
        (_arclines_as_list, ["layer 'arcline_path_3' is a JSON object"]),
    ],
)
def test_a_malformed_map_expansion_is_refused_by_layer_row_and_field_before_any_clip(tmp_path, capsys, edit, names):
    root = mini.write_mini_nuscenes(tmp_path / "ns")
    layers = json.loads(mini.map_file(root).read_text())
    edit(layers)
    mini.map_file(root).write_text(json.dumps(layers))
    out = tmp_path / "out"
    assert main(["import", "nuscenes", "--dataroot", str(root), "--out", str(out), "--preset", "tiny"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{mini.map_file(root)}: " in err
    for name in names:
        assert name in err
    assert not out.exists()


@pytest.mark.parametrize("first, then", [("tiny", "default"), ("default", "tiny")])
def test_a_dataset_keeps_the_preset_of_its_first_clip(tmp_path, capsys, first, then):
    root = mini.write_mini_nuscenes(tmp_path / "ns")
    out = tmp_path / "out"
    base = ["import", "nuscenes", "--dataroot", str(root), "--out", str(out)]
    assert main([*base, "--scenes", "scene-0001", "--preset", first]) == 0
    capsys.readouterr()
    assert main([*base, "--scenes", "scene-0002", "--preset", then]) == 2
    err = capsys.readouterr().err
    assert f"--preset {then}: {out} holds clips at preset {first!r}" in err and f"preset {then!r}: " in err
    assert list_clips(out) == ["nuscenes_scene-0001"] and not (out / "nuscenes_scene-0002").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (["--out", "FILE"], "--out FILE is a file"),
        (["--out", "OUT", "--scenarios", "FILE"], "--scenarios FILE is a file"),
        (["--out", "OUT", "--preset", "huge"], "--preset: unknown preset 'huge'"),
    ],
)
def test_import_flags_are_refused_by_name_before_any_work(tmp_path, capsys, args, message):
    root = mini.write_mini_nuscenes(tmp_path / "ns")
    (tmp_path / "FILE").write_text("not a folder")
    args = [str(tmp_path / a) if a in ("FILE", "OUT") else a for a in args]
    assert main(["import", "nuscenes", "--dataroot", str(root), *args]) == 2
    assert message.replace("FILE", str(tmp_path / "FILE")) in capsys.readouterr().err
    assert not (tmp_path / "OUT").exists()


def test_documented_install_is_what_make_install_runs():
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    doc = (root / "docs" / "data.md").read_text()
    makefile = (root / "Makefile").read_text()
    assert "pip install --no-deps nuscenes-devkit==1.2.0" in doc
    assert "-m pip install -q --no-deps nuscenes-devkit==1.2.0" in makefile
    assert ",nuscenes]" in makefile and '".[nuscenes]"' in doc


@pytest.fixture(scope="module")
def replay_files(imported, tmp_path_factory):
    root, _ = imported
    out = tmp_path_factory.mktemp("replay_clips")
    scen = tmp_path_factory.mktemp("replay_scenarios")
    args = ["import", "nuscenes", "--dataroot", str(root), "--out", str(out), "--scenarios", str(scen)]
    assert main(args) == 0
    return sorted(scen.glob("*.yaml"))


def test_replay_scenario_places_logged_agents_around_the_ego(replay_files):
    from m4world_env.replay import REPLAY_BEHIND_M
    from m4world_env.scenario import load_scenario

    assert [p.name for p in replay_files] == ["replay_nuscenes_scene-0001.yaml", "replay_nuscenes_scene-0002.yaml"]
    s = load_scenario(replay_files[0])
    assert s.ego.speed == pytest.approx(mini.EGO_SPEED, abs=1e-3)
    assert s.duration == pytest.approx(1.0)
    # The policies' target speed is the ego's mean logged speed.
    # (The 10 Hz frames take the nearest sweep, so the logged distance is the sweeps' 0 to 1 s.)
    assert s.road.speed_limit == pytest.approx(mini.EGO_SPEED, abs=1e-3)
    # Poses are in the ego's logged start frame: the ego at the origin, heading +x.
    by_cat = {o.category: o for o in s.objects}
    car = by_cat["car"].track  # keeps pace with the ego: waypoints 20 m ahead of it, 2 m left
    assert car.kind == "waypoints"
    assert car.points[0].x == pytest.approx(mini.CAR_IN_EGO[0] - mini.LIDAR_IN_EGO[0], abs=1e-3)
    assert car.points[0].y == pytest.approx(mini.CAR_IN_EGO[1], abs=1e-3)
    assert car.points[-1].x - car.points[0].x == pytest.approx(mini.EGO_SPEED * car.points[-1].t, abs=1e-2)
    assert by_cat["barrier"].track.kind == "static"  # the animal does not move
    # No map at this location: three lanes along the logged path, the ego in the middle at its start.
    assert s.road.type == "route" and s.road.source == "ego_path" and len(s.road.lanes) == 3
    assert (s.ego.lane, s.ego.longitudinal) == (1, pytest.approx(REPLAY_BEHIND_M, abs=1e-3))
    assert s.road.reference_path[0] == pytest.approx((0.0, 0.0)) and s.road.reference_path[-1] == pytest.approx(
        (mini.EGO_SPEED, 0.0)
    )


def _local(point: tuple[float, float]) -> np.ndarray:
    """A global point of scene-0002 in its replay frame (the ego's logged start: LIDAR_TOP, heading north)."""
    start = np.array([mini.EGO_START[0], mini.EGO_START[1] + mini.LIDAR_IN_EGO[0]])
    d = np.asarray(point) - start
    return np.array([d[1], -d[0]])  # heading north: forward = +y, left = -x


def test_replay_road_follows_the_map_lanes(imported, replay_files):
    from m4world_env.scenario import load_scenario
    from m4world_env.traffic.polyline import Polyline

    _, out = imported
    meta = read_clip(out, "nuscenes_scene-0002").meta
    assert meta["route_lanes"] == ["lane_in", "turn_left", "lane_out"]  # not the oncoming lane
    s = load_scenario(replay_files[1])
    assert s.road.source == "map_expansion" and len(s.road.lanes) == 1
    assert s.road.lane_width == pytest.approx(mini.LANE_WIDTH)  # lane_in's polygon area / length
    lane = Polyline.from_points(s.road.lanes[0])
    # The lane runs through the connector's centerline half-way round the turn, and ends on lane_out.
    _, lateral = lane.project(_local(mini.turn_point(np.pi / 4))[None])
    assert abs(lateral[0]) < 0.01
    assert lane.points[-1] == pytest.approx(_local((mini.LANE_OUT_END_X, mini.TURN_CENTRE[1] + mini.TURN_RADIUS)))
    # The ego starts on it, where it was logged (LIDAR_TOP, 0.94 m ahead on the tangent: 4.4 cm outside).
    s_ego, r_ego = lane.project(np.zeros((1, 2)))
    assert r_ego[0] == pytest.approx(-(np.hypot(mini.TURN_RADIUS, mini.LIDAR_IN_EGO[0]) - mini.TURN_RADIUS), abs=1e-3)
    assert s.ego.longitudinal == pytest.approx(s_ego[0], abs=1e-3)
    # The map expansion is drawn around it: both drivable polygons, the two dividers.
    assert len(s.road.map.drivable_area) == 2 and len(s.road.map.lane_lines) == 2


def _stop(env):
    return lambda obs, info: np.array([-1.0, 0.0], dtype=np.float32)


@pytest.mark.parametrize("backend", ["procedural", "world_model"])
def test_replay_on_the_map_scores_progress_along_the_logged_route(replay_files, backend, tiny_bundle):
    import gymnasium as gym

    from m4world_env.evaluate import EvalRequest, evaluate, format_table
    from m4world_env.scenario import load_scenario

    kwargs = {"checkpoint": str(tiny_bundle)} if backend == "world_model" else {}
    path = str(replay_files[1])
    runs = [
        evaluate(EvalRequest("lane_keeping", [path], episodes=1, seed=3, backend=backend, **kwargs)) for _ in range(2)
    ]
    assert runs[0] == runs[1]
    follow = runs[0]["episodes"][0]
    assert follow["steps"] == 5  # 1 s of log at 5 decisions per second: run to the end
    # Following the lane round the turn covers the logged route (5 m in 1 s) and stays on it.
    assert follow["route_progress"] == pytest.approx(1.0, abs=0.05) and follow["progress"] == follow["route_progress"]
    assert follow["off_route"] == 0.0 and follow["off_road"] == 0.0 and follow["collision"] == 0.0
    assert follow["route_deviation_max_m"] < 1.0  # the controller lags into a 10 m radius turn
    stop = evaluate(EvalRequest(_stop, [path], episodes=1, seed=3, backend=backend, **kwargs))["episodes"][0]
    assert stop["route_progress"] < 0.6 and stop["pdms"] < follow["pdms"]
    assert "off_route" in format_table(runs[0]).splitlines()[0]
    env = gym.make("M4World-v0", scenario=load_scenario(path), backend=backend, **kwargs)
    _, info = env.reset(seed=0)
    assert info["road_source"] == "map_expansion"
    env.close()


@pytest.mark.parametrize("backend", ["procedural", "world_model"])
def test_replay_scenario_runs_to_its_end_and_scores_deterministically(replay_files, backend, tiny_bundle):
    from m4world_env.evaluate import EvalRequest, evaluate

    kwargs = {"checkpoint": str(tiny_bundle)} if backend == "world_model" else {}
    runs = [
        evaluate(EvalRequest("idm", [str(replay_files[0])], episodes=1, seed=3, backend=backend, **kwargs))
        for _ in range(2)
    ]
    assert runs[0] == runs[1]
    episode = runs[0]["episodes"][0]
    assert episode["steps"] == 5  # 1 s of log at 5 decisions per second: run to the end
    # The logged car 20 m ahead straddles the lane line: IDM brakes for it and changes lanes.
    assert 0.0 <= episode["pdms"] <= 1.0 and 0.0 < episode["route_progress"] < 1.0
    assert episode["route_deviation_max_m"] < 4.0 and episode["off_route"] == 0.0


def test_ego_speed_comes_from_the_logged_poses(imported):
    _, out = imported
    assert read_clip(out, "nuscenes_scene-0001").frames[0].ego.speed == pytest.approx(mini.EGO_SPEED)
