import numpy as np

from m4world_env.cli import main
from world_model.data import list_clips, read_clip


def test_record_cli_writes_loadable_clips_and_resumes(tmp_path, capsys):
    out = tmp_path / "clips"
    args = [
        "record",
        "--scenario",
        "merge_cut_in",
        "tree_truck_highway",
        "--episodes",
        "2",
        "--duration",
        "1.0",
        "--out",
        str(out),
        "--height",
        "32",
        "--width",
        "56",
    ]
    assert main(args) == 0
    names = list_clips(out)
    assert len(names) == 4 and len(set(names)) == 4
    clip = read_clip(out, names[0])
    assert clip.cameras.shape[1:] == (6, 32, 56, 3) and clip.cameras.dtype == np.uint8
    assert clip.lidar.shape[1:] == (32, 1024)
    assert clip.num_frames == clip.cameras.shape[0] == clip.bev.shape[0] >= 10
    assert clip.frames[0].rig.resolution == (32, 56)
    assert abs(clip.fps - 10.0) < 1e-6
    # randomization is seeded per episode: two episodes of one scenario differ, a re-run is identical
    a, b = read_clip(out, names[0]), read_clip(out, names[1])
    assert a.frames[0].prompt != b.frames[0].prompt or not np.array_equal(a.cameras[0], b.cameras[0])
    # reference crops ("image descriptions") exist for visible objects, keyed by track id
    assert any(clip_i.crops for clip_i in (read_clip(out, n) for n in names))
    track_ids = {o.track_id for fr in clip.frames for o in fr.objects}
    assert set(clip.crops) <= track_ids
    # a restarted recording skips complete clips (mtime unchanged) and rebuilds a missing one
    first_meta = out / names[0] / "meta.json"
    mtime = first_meta.stat().st_mtime_ns
    import shutil

    shutil.rmtree(out / names[3])
    assert main(args) == 0
    assert first_meta.stat().st_mtime_ns == mtime
    assert list_clips(out) == names
    assert "4 clips" in capsys.readouterr().out


def _record_args(out, *scenarios, height=32, extra=()):
    return [
        "record",
        "--scenario",
        *scenarios,
        "--duration",
        "0.5",
        "--out",
        str(out),
        "--height",
        str(height),
        "--width",
        "56",
        *extra,
    ]


def test_resuming_with_other_settings_is_refused_not_mixed(tmp_path, capsys):
    out = tmp_path / "clips"
    assert main(_record_args(out, "empty_highway")) == 0
    before = list_clips(out)
    assert main(_record_args(out, "empty_highway", "merge_cut_in", height=48)) == 2
    err = capsys.readouterr().err
    assert "height: recorded 32, now 48" in err and "another --out" in err
    assert list_clips(out) == before  # nothing was written
    assert main(_record_args(out, "empty_highway", extra=["--no-randomize"])) == 2
    assert "randomize: recorded True, now False" in capsys.readouterr().err
    assert main(_record_args(out, "empty_highway", "merge_cut_in")) == 0  # same settings: resumes
    assert len(list_clips(out)) == 2


def test_clip_seeds_do_not_depend_on_the_scenario_list(tmp_path, capsys):
    alone, listed = tmp_path / "alone", tmp_path / "listed"
    assert main(_record_args(alone, "merge_cut_in")) == 0
    assert main(_record_args(listed, "empty_highway", "merge_cut_in")) == 0
    (name,) = list_clips(alone)
    assert name in list_clips(listed)
    assert np.array_equal(read_clip(alone, name).cameras, read_clip(listed, name).cameras)
    assert main(_record_args(tmp_path / "twice", "merge_cut_in", "merge_cut_in")) == 2
    assert "given more than once" in capsys.readouterr().err


def test_excluding_a_category_removes_it(tmp_path):
    out = tmp_path / "base"
    args = [
        "record",
        "--scenario",
        "tree_truck_highway",
        "highway_dense_rain_dusk",
        "--episodes",
        "3",
        "--duration",
        "0.5",
        "--out",
        str(out),
        "--height",
        "32",
        "--width",
        "56",
        "--exclude-category",
        "tree_truck",
    ]
    assert main(args) == 0
    for name in list_clips(out):
        clip = read_clip(out, name)
        assert all(o.category != "tree_truck" for fr in clip.frames for o in fr.objects)


def test_randomized_traffic_mix_can_draw_every_vehicle_category():
    from m4world_env.recorder import exclude_categories
    from m4world_env.scenario import load_scenario, randomize_scenario

    s = randomize_scenario(load_scenario("highway_dense_rain_dusk"), np.random.default_rng(0))
    assert s.traffic.mix.get("tree_truck", 0) > 0  # so the exclusion below is not vacuous
    assert "tree_truck" not in exclude_categories(s, ["tree_truck"]).traffic.mix


def test_record_with_two_workers_writes_the_serial_runs_files_byte_for_byte(tmp_path):
    import hashlib

    def digest(root):
        return {
            str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*"))
            if p.is_file()
        }

    scenarios = ("merge_cut_in", "empty_highway")
    args = [*_record_args(tmp_path / "serial", *scenarios), "--episodes", "2"]
    assert main(args) == 0
    assert main([*_record_args(tmp_path / "parallel", *scenarios), "--episodes", "2", "--workers", "2"]) == 0
    serial, parallel = digest(tmp_path / "serial"), digest(tmp_path / "parallel")
    assert len(list_clips(tmp_path / "serial")) == 4
    assert serial == parallel  # every clip file, recording.json and dataset.json (the recording order)


def test_a_clip_written_but_not_registered_is_registered_when_resumed(tmp_path):
    import json

    out = tmp_path / "clips"
    assert main(_record_args(out, "empty_highway", "merge_cut_in")) == 0
    names = list_clips(out)
    index = json.loads((out / "dataset.json").read_text())
    index["clips"] = index["clips"][:1]  # as if the recording was killed between writing and registering
    (out / "dataset.json").write_text(json.dumps(index))
    assert main([*_record_args(out, "empty_highway", "merge_cut_in"), "--workers", "2"]) == 0
    assert list_clips(out) == names


def _ego_track(style: str, seed: int, action_type: str = "continuous", duration: float = 20.0):
    from m4world_env.recorder import RecordConfig, drive_episode
    from m4world_env.scenario import load_scenario

    cfg = RecordConfig(scenarios=["highway_sunny_day"], duration=duration, action_type=action_type, styles=(style,))
    frames = drive_episode(load_scenario("highway_sunny_day"), seed, cfg)
    speeds = np.array([f.ego.speed for f in frames])
    lanes = [f.ego.lane_id for f in frames]
    return frames, float(np.ptp(speeds)), sum(a != b for a, b in zip(lanes, lanes[1:], strict=False))


def test_driving_styles_brake_accelerate_and_change_lanes_deterministically():
    steady, steady_range, steady_changes = _ego_track("steady", 3)
    _, speed_range, _ = _ego_track("speed_changes", 3)
    weaving, _, weaving_changes = _ego_track("weaving", 3)
    assert speed_range > steady_range + 3.0  # m/s: it brakes and speeds up again
    assert weaving_changes >= steady_changes + 5  # back and forth between lanes
    again, _, _ = _ego_track("weaving", 3)
    assert [f.to_dict() for f in again] == [f.to_dict() for f in weaving]


def test_record_cycles_styles_over_episodes_and_refuses_unknown_ones(tmp_path, capsys):
    import pytest

    from m4world_env.recorder import RecordConfig, content_settings

    out = tmp_path / "mix"
    styles = ["--styles", "steady", "weaving", "--action-type", "continuous", "--episodes", "2"]
    assert main(_record_args(out, "empty_highway", extra=styles)) == 0
    got = sorted(read_clip(out, n).meta["ego_style"] for n in list_clips(out))
    assert got == ["steady", "weaving"]
    assert main(_record_args(out, "empty_highway", extra=["--episodes", "2"])) == 2  # a mix is a content setting
    assert "styles: recorded ['steady', 'weaving'], now None" in capsys.readouterr().err
    assert "styles" not in content_settings(RecordConfig(scenarios=["x"]))  # datasets from before styles resume
    assert main(_record_args(tmp_path / "bad", "empty_highway", extra=["--styles", "zigzag"])) == 2
    assert "unknown driving style 'zigzag'" in capsys.readouterr().err
    with pytest.raises(ValueError, match="at least one driving style"):
        RecordConfig(scenarios=["x"], styles=())
