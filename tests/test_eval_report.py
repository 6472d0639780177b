"""Report plumbing and the shipped judge, on a tiny freshly recorded dataset: the Oracle scores
perfectly on Table 1, corrupted Oracles score lower, and the shipped judge answers ground-truth
questions correctly."""

import json

import numpy as np
import pytest

from m4world_env.evalset import EvalsetConfig, record_evalset
from world_model.data import read_clip
from world_model.eval import Generated, evaluate_rows, format_markdown, load_default_judge, oracle_row, write_report
from world_model.eval.corrupt import blur, color_shift
from world_model.eval.crops import extract_crops
from world_model.eval.report import ReportConfig
from world_model.eval.report.markdown import chunk_jumps_per_clip
from world_model.scene import CATEGORIES
from world_model.sim import ProceduralSimulator


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    root = tmp_path_factory.mktemp("evalset")
    cfg = EvalsetConfig(
        scenarios=(),
        short_duration=3.0,
        grid_scenarios=("highway_sunny_day", "two_way_overtake_dusk"),
        grid_weathers=("sunny",),
        grid_times=("day", "dusk"),
        long_scenarios=(),
        base_seed=7000,
    )
    return [read_clip(root, e["name"]) for e in record_evalset(root, cfg, progress=False)]


@pytest.fixture(scope="module")
def judge():
    return load_default_judge()


def test_shipped_judge_answers_ground_truth_existence(clips, judge):
    sim = ProceduralSimulator()
    crops = [c for clip in clips for i in range(0, clip.num_frames, 3)
             for c in extract_crops(clip.frames[i], np.asarray(clip.cameras[i]), sim, judge.crop_config)]  # fmt: skip
    assert len(crops) >= 20
    images = [c.image for c in crops]
    true = judge.is_category(images, [c.category for c in crops])
    wrong_cats = [CATEGORIES[(CATEGORIES.index(c.category) + 5) % len(CATEGORIES)] for c in crops]
    wrong = judge.is_category(images, wrong_cats)
    assert true.mean() >= 0.7, f"yes for the true category on only {true.mean():.2f}"
    assert (~wrong).mean() >= 0.9, f"no for a wrong category on only {(~wrong).mean():.2f}"
    with pytest.raises(ValueError, match="unknown category"):
        judge.is_category(images[:1], ["spaceship"])


def test_oracle_beats_corrupted_rows(clips, judge, tmp_path):
    rows = {
        "oracle": oracle_row,
        "blurred": lambda c: Generated(blur(np.asarray(c.cameras), 2.0), np.asarray(c.lidar, np.float32) + 2.0),
        "color_shifted": lambda c: Generated(color_shift(np.asarray(c.cameras))),
    }
    # 3 s clips with a 1 s long-horizon window: every clip also gets the long-horizon curves
    cfg = ReportConfig(frame_stride=2, clip_window=5, lidar_stride=15, chamfer_max_points=2048, long_window_s=1)
    report = evaluate_rows(rows, clips, judge=judge, config=cfg)
    o, b, s = (report.rows[k] for k in rows)
    t1 = o.table1
    assert t1.frechet_judge_frame == pytest.approx(0.0, abs=1e-6)
    assert t1.frechet_judge_clip == pytest.approx(0.0, abs=1e-6)
    assert t1.psnr_db == cfg.psnr_cap_db and t1.ssim == pytest.approx(1.0)
    assert t1.lidar_range_mae_m == 0.0 and t1.lidar_chamfer_m == 0.0
    for bad in (b, s):
        assert bad.table1.frechet_judge_frame > 0 and bad.table1.frechet_judge_clip > 0
        assert bad.table1.psnr_db < 40
        assert np.mean(list(bad.table2.to_json().values())) < np.mean(list(o.table2.to_json().values()))
    assert b.table1.lidar_range_mae_m == pytest.approx(2.0, abs=1e-3)
    assert b.table1.lidar_range_mae_first_s_m == pytest.approx(2.0, abs=1e-3)
    assert t1.lidar_range_mae_first_s_m == 0.0
    for lo, lb in zip(o.long_horizon, b.long_horizon, strict=True):
        assert lo.seconds == 3 and lo.ratio_last_first == 1.0 and lo.frechet.first < 1e-6
        assert lo.lidar_mae_per_second == (0.0,) * 3
        assert lb.frechet.first > 0 and lb.frechet.ratio > 0
        assert lb.lidar_mae_per_second == pytest.approx([2.0] * 3, abs=1e-3)
    assert s.table1.lidar_range_mae_m is None
    assert b.table2.clarity < o.table2.clarity
    assert s.table2.textual_fidelity < o.table2.textual_fidelity
    assert o.per_category["existence"]  # grouped by category

    md = format_markdown(report)
    assert "| oracle |" in md and "| blurred |" in md and "Table 2" in md
    md_path, json_path = write_report(report, tmp_path)
    written = json.loads(json_path.read_text())
    assert written["rows"].keys() == rows.keys() and written == report.to_json()
    assert md_path.read_text() == md


def test_rows_with_wrong_shapes_are_rejected(clips, judge):
    with pytest.raises(ValueError, match="cameras must be uint8"):
        evaluate_rows({"bad": lambda c: Generated(np.asarray(c.cameras)[:, :2])}, clips[:1], judge=judge)


def test_finished_rows_are_cached_by_key(clips, judge, tmp_path):
    calls = []

    def counted(clip):
        calls.append(clip.name)
        return oracle_row(clip)

    cfg = ReportConfig(frame_stride=4, lidar_stride=30, chamfer_max_points=512)
    two = clips[:2]
    first = evaluate_rows({"a": counted, "b": counted}, two, judge, cfg, cache_dir=tmp_path, row_ids={"a": "A"})
    assert len(calls) == 4 and (tmp_path / "a.json").exists() and not (tmp_path / "b.json").exists()
    again = evaluate_rows({"a": counted}, two, judge, cfg, cache_dir=tmp_path, row_ids={"a": "A"})
    assert len(calls) == 4 and again.rows["a"] == first.rows["a"]  # reused, not regenerated
    # Another generator id, other clips or another config: generated again.
    evaluate_rows({"a": counted}, two, judge, cfg, cache_dir=tmp_path, row_ids={"a": "A2"})
    evaluate_rows({"a": counted}, clips[:1], judge, cfg, cache_dir=tmp_path, row_ids={"a": "A2"})
    evaluate_rows(
        {"a": counted}, clips[:1], judge, ReportConfig(frame_stride=3), cache_dir=tmp_path, row_ids={"a": "A2"}
    )
    assert len(calls) == 4 + 2 + 1 + 1


def test_chunk_jump_scores_rows_generated_in_passes(clips, judge):
    def shifted_every_pass(clip):  # the recording, brightened by a new amount in every 3-frame pass
        cams = np.asarray(clip.cameras).astype(np.int16)
        starts = tuple(range(1, clip.num_frames, 3))
        for i, s in enumerate(starts):
            cams[s:] += 30 if i % 2 == 0 else -30
        lidar = np.asarray(clip.lidar, np.float32)
        return Generated(np.clip(cams, 0, 255).astype(np.uint8), lidar, pass_starts=starts)

    rows = {
        "oracle": oracle_row,
        "oracle_in_passes": lambda c: Generated(np.asarray(c.cameras), np.asarray(c.lidar, np.float32), (1, 4, 7)),
        "flicker": shifted_every_pass,
    }
    cfg = ReportConfig(frame_stride=6, lidar_stride=30, chamfer_max_points=512)
    report = evaluate_rows(rows, clips, judge=judge, config=cfg)
    t1 = {k: r.table1 for k, r in report.rows.items()}
    assert t1["oracle"].chunk_jump_cameras is None and t1["oracle"].chunk_jump_lidar is None
    assert t1["oracle_in_passes"].chunk_jump_cameras == pytest.approx(1.0)  # the recording's own motion
    assert t1["oracle_in_passes"].chunk_jump_lidar == pytest.approx(1.0)
    assert t1["flicker"].chunk_jump_cameras > 2.0 and t1["flicker"].chunk_jump_lidar == pytest.approx(1.0)
    jumps = report.rows["flicker"].chunk_jumps["cameras"]
    assert jumps.generated > jumps.recording > 0
    per_clip = report.rows["flicker"].chunk_jumps_per_clip
    assert tuple(c.clip for c in per_clip) == report.clips and all(c.chunk_jump_cameras > 1.5 for c in per_clip)
    assert report.rows["oracle"].chunk_jumps_per_clip == ()
    md = format_markdown(report)
    assert "chunk_jump_cameras" in md and "### Chunk jumps per clip" in md
    n = len(clips)
    vs = "\n".join(chunk_jumps_per_clip(report, reference="oracle_in_passes"))
    assert f"| flicker | {n} | " in vs and f", {n} of {n} |" in vs  # jumps more than the recording on every clip
    assert f"| flicker | {n} |" in md and "| oracle |" not in md.split("### Chunk jumps per clip")[1]


def test_object_scores_see_a_row_that_drops_the_objects(clips, judge):
    """The recording re-rendered without its objects (the report's road-only row): the whole frame
    barely changes (objects are a few percent of the pixels), the object-region PSNR and LiDAR MAE
    and the judge's existence answers do."""
    from world_model.eval.report import road_only_row

    cfg = ReportConfig(frame_stride=2, clip_window=5, lidar_stride=3, chamfer_max_points=2048)
    report = evaluate_rows({"oracle": oracle_row, "road_only": road_only_row}, clips, judge=judge, config=cfg)
    o, n = (report.rows[k].table1 for k in ("oracle", "road_only"))
    assert o.object_psnr_db == cfg.psnr_cap_db and o.lidar_object_mae_m == 0.0
    assert n.psnr_db - n.object_psnr_db > 10.0, n
    assert n.lidar_object_mae_m > 3.0 * n.lidar_range_mae_m, n
    assert report.rows["road_only"].table2.existence < 0.5 * report.rows["oracle"].table2.existence
    assert "object_psnr_db" in format_markdown(report)


def test_motion_scores_tell_a_frozen_row_from_the_recording(clips, judge):
    """The recording moves exactly as much as itself; its first frame held still does not move at
    all, whatever its errors; a row halfway between the two moves half as much."""
    from world_model.eval.report import first_frame_row

    def halfway(clip):  # every frame averaged with the first: half of every change
        cams, lid = np.asarray(clip.cameras, np.float64), np.asarray(clip.lidar, np.float64)
        return Generated(np.rint((cams + cams[:1]) / 2).astype(np.uint8), ((lid + lid[:1]) / 2).astype(np.float32))

    cfg = ReportConfig(frame_stride=2, clip_window=5, lidar_stride=3, chamfer_max_points=2048, motion_lag_s=0.5)
    rows = {"oracle": oracle_row, "first_frame": first_frame_row, "halfway": halfway}
    report = evaluate_rows(rows, clips, judge=judge, config=cfg)
    t1 = {k: r.table1 for k, r in report.rows.items()}
    assert t1["oracle"].motion_cameras == 1.0 and t1["oracle"].motion_lidar == 1.0
    assert t1["first_frame"].motion_cameras == 0.0 and t1["first_frame"].motion_lidar == 0.0
    assert t1["halfway"].motion_lidar == pytest.approx(0.5, rel=1e-5)
    assert t1["halfway"].motion_cameras == pytest.approx(0.5, abs=0.05)  # rounded to uint8
    assert "motion_cameras" in format_markdown(report)


def test_simulator_object_masks_are_the_visible_object_pixels_and_returns(clips):
    from dataclasses import replace

    sim = ProceduralSimulator()
    frame = next(f for c in clips for f in c.frames if len(f.objects) >= 2)
    cams, lidar = sim.object_masks(frame)
    visible, _ = sim.visible_pixels(frame)
    assert cams.shape == (frame.rig.num_views, *frame.rig.resolution)
    np.testing.assert_array_equal(cams.sum(axis=(1, 2)), visible.sum(axis=1))
    ranges = sim.render_lidar(frame)
    road = sim.render_lidar(replace(frame, objects=()))
    assert lidar.any() and (ranges[lidar] > 0).all()
    assert ((ranges[lidar] < road[lidar]) | (road[lidar] == frame.lidar.no_return)).all()
    none_cams, none_lidar = sim.object_masks(replace(frame, objects=()))
    assert not none_cams.any() and not none_lidar.any()


def test_a_row_of_several_seeds_is_their_mean(clips, judge, tmp_path):
    shifted = [lambda c, k=k: Generated(color_shift(c.cameras, k + 1), c.lidar) for k in range(2)]
    report = evaluate_rows(
        {"shift": shifted, "shift0": shifted[0], "shift1": shifted[1]},
        clips[:1],
        judge=judge,
        config=ReportConfig(frame_stride=10),
        cache_dir=tmp_path,
        row_ids={"shift": "shift-test"},
    )
    rows = report.rows
    assert rows["shift"].seeds == 2 and rows["shift0"].seeds is None
    psnrs = [rows[r].table1.psnr_db for r in ("shift0", "shift1")]
    assert rows["shift"].table1.psnr_db == pytest.approx(sum(psnrs) / 2)
    assert rows["shift"].spread.table1.psnr_db == pytest.approx(abs(psnrs[0] - psnrs[1]) / 2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["shift.seed0.json", "shift.seed1.json"]
