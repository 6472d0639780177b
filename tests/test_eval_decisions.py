"""What a policy reads (world_model.eval.decisions and its place in the report), on range maps and
class maps built by hand: the nearest object per LiDAR sector, the lead vehicle's bottom row and
range in FRONT, the lane markings' lateral position, pooled and shown per row."""

import json
from dataclasses import replace

import numpy as np
import pytest

from world_model.eval.decisions import (
    BEAM_BANDS,
    CLOSE_RANGE_M,
    MARKING,
    VEHICLE,
    ClipDecisions,
    DecisionSums,
    LaneSums,
    LeadSums,
    LeadVehicle,
    SectorSums,
    camera_decisions,
    lane_errors,
    lane_marking_offsets,
    lead_errors,
    lead_vehicle,
    lidar_decisions,
    nearest_object_range_per_sector,
    non_ground_returns,
    pool_seconds,
    sector_centres_deg,
    sector_count,
    sector_of_columns,
    sector_range_errors,
)
from world_model.eval.report import DecisionScores, Report, ReportConfig, RowScores, format_markdown
from world_model.eval.report.row_scores import decision_figures, row_scores
from world_model.eval.report.seeds import average_seeds
from world_model.sensors import CameraSpec, LidarSpec, road_points

SPEC = LidarSpec()  # 32 beams +10..-30 deg, 1024 columns, 1.84 m above the road
HORIZON, LOW, ALL = BEAM_BANDS
AHEAD = slice(500, 525)  # columns around straight ahead (512), all in sector 0


def flat_road(spec: LidarSpec = SPEC) -> np.ndarray:
    """The range map of the flat road alone: mount_height / sin(-elevation) on the downward beams
    that reach the road within max_range, no return elsewhere."""
    el = spec.elevations()
    with np.errstate(divide="ignore"):
        r = np.where(el < 0, spec.mount_height / -np.sin(el), np.inf)
    r = np.where(r <= spec.max_range, r, spec.no_return)
    return np.repeat(r[:, None], spec.azimuth, axis=1)


def with_box(ranges: np.ndarray, rows: slice, cols: slice, r: float) -> np.ndarray:
    out = ranges.copy()
    out[rows, cols] = r
    return out


HORIZON_ROWS = slice(7, 10)  # +0.97, -0.32, -1.61 deg


# ------------------------------------------------------------------------------ LiDAR sectors


def test_beam_bands_and_sectors_on_the_default_lidar():
    # Row k is at 10 - 40 k / 31 deg: rows 7-9 lie within +-2 deg, rows 10-19 in -2.9..-14.5 deg.
    assert np.flatnonzero(HORIZON.beams(SPEC)).tolist() == [7, 8, 9]
    assert np.flatnonzero(LOW.beams(SPEC)).tolist() == list(range(10, 20))
    assert ALL.beams(SPEC).all()
    assert sector_count() == 12 and sector_centres_deg().tolist() == [0, 30, 60, 90, 120, 150, 180, -150, -120,
                                                                         -90, -60, -30]  # fmt: skip
    sectors = sector_of_columns(SPEC)
    # Column c looks at (512 - c) x 0.3515625 deg: sector 0 (-15..+15 deg) is columns 470..554.
    assert sectors[512] == 0 and sectors[470] == 0 and sectors[554] == 0
    assert sectors[469] == 1 and sectors[555] == 11  # left of ahead is sector 1, right is the last
    assert sectors[0] == 6 and sectors[1023] == 6  # straight behind, on both ends of the map
    assert sectors[256] == 3  # +90 deg: the left side
    # 85.33 columns a sector: edges at +45 deg (column 384), +135 deg (128), -105 deg (811), ...
    # fall on a column, which belongs to the sector counter-clockwise of the edge.
    assert sectors[384] == 2 and sectors[385] == 1 and sectors[128] == 5 and sectors[811] == 8
    assert np.bincount(sectors).tolist() == [85, 85, 86, 85, 85, 86, 85, 85, 86, 85, 85, 86]
    with pytest.raises(ValueError, match="divide 360"):
        sector_count(25.0)


def test_the_flat_road_alone_holds_no_object():
    road = flat_road()
    assert not non_ground_returns(road, SPEC).any()
    for band in BEAM_BANDS:
        assert np.isnan(nearest_object_range_per_sector(road, SPEC, band)).all()
        assert sector_range_errors(road, road, SPEC, band) == SectorSums(objects=0, empty=12)


def test_ground_removal_is_a_height_above_the_road():
    road = flat_road()
    row = 20  # -15.806 deg: the road at 1.84 / sin(15.806 deg) = 6.76 m
    el = SPEC.elevations()[row]
    low, high = (SPEC.mount_height - 0.2) / -np.sin(el), (SPEC.mount_height - 0.5) / -np.sin(el)
    ranges = road.copy()
    ranges[row, 512], ranges[row, 513] = low, high  # 0.2 m and 0.5 m above the road
    kept = non_ground_returns(ranges, SPEC)
    assert np.flatnonzero(kept).tolist() == [row * SPEC.azimuth + 513]
    # 0.3 m above the road on the flat road is 1 - 0.3 / 1.84 of the beam's road range
    at = (1 - 0.3 / SPEC.mount_height) * road[row, 0]
    assert not non_ground_returns(with_box(road, slice(row, row + 1), slice(0, 1), at * 1.001), SPEC)[row, 0]
    assert non_ground_returns(with_box(road, slice(row, row + 1), slice(0, 1), at * 0.999), SPEC)[row, 0]
    with pytest.raises(ValueError, match=r"range map must be \(32, 1024\)"):
        non_ground_returns(road[:8], SPEC)


def test_a_car_ahead_drawn_at_28_m_instead_of_10_m():
    road = flat_road()
    truth = with_box(road, HORIZON_ROWS, AHEAD, 10.0)  # a box of returns 10 m ahead on the horizon beams
    model = with_box(road, HORIZON_ROWS, AHEAD, 28.0)
    near = nearest_object_range_per_sector(truth, SPEC, HORIZON)
    assert near[0] == 10.0 and np.isnan(near[1:]).all()
    assert np.isnan(nearest_object_range_per_sector(truth, SPEC, LOW)).all()  # the low beams see the road
    expected = SectorSums(errors_m=(18.0,), objects=1, farther=1, missed=0, empty=11, phantom=0, close=1, close_off=1)
    assert sector_range_errors(truth, model, SPEC, HORIZON) == expected
    assert sector_range_errors(truth, model, SPEC, ALL) == expected
    assert sector_range_errors(truth, model, SPEC, LOW) == SectorSums(objects=0, empty=12)
    # 4 m farther is within the tolerance: an error, not a "farther"
    close = sector_range_errors(truth, with_box(road, HORIZON_ROWS, AHEAD, 14.0), SPEC, HORIZON)
    assert close == SectorSums(errors_m=(4.0,), objects=1, farther=0, empty=11, close=1, close_off=1)


def test_the_close_field_is_read_to_a_tenth_of_a_metre():
    road = flat_road()
    truth = with_box(road, HORIZON_ROWS, AHEAD, 3.0)  # a car 3 m away, as one alongside is
    for model_m, off in ((2.85, 1), (3.05, 0), (3.0, 0)):
        sums = sector_range_errors(truth, with_box(road, HORIZON_ROWS, AHEAD, model_m), SPEC, HORIZON)
        assert (sums.close, sums.close_off) == (1, off), model_m
    # beyond CLOSE_RANGE_M a tenth of a metre is no matter; missing a close object is
    far = with_box(road, HORIZON_ROWS, AHEAD, CLOSE_RANGE_M + 1.0)
    assert sector_range_errors(far, with_box(road, HORIZON_ROWS, AHEAD, CLOSE_RANGE_M + 1.5), SPEC, HORIZON).close == 0
    assert sector_range_errors(truth, road, SPEC, HORIZON).close_off == 1


def test_a_missing_object_and_a_phantom():
    road = flat_road()
    truth = with_box(road, HORIZON_ROWS, AHEAD, 10.0)
    missed = SectorSums(objects=1, missed=1, empty=11, close=1, close_off=1)
    assert sector_range_errors(truth, road, SPEC, HORIZON) == missed
    assert sector_range_errors(road, truth, SPEC, HORIZON) == SectorSums(objects=0, empty=12, phantom=1)
    # An object beyond 40 m is not scored; the row drawing it 12 m nearer (at 33 m) is a phantom.
    far = with_box(road, HORIZON_ROWS, AHEAD, 45.0)
    assert sector_range_errors(far, far, SPEC, HORIZON) == SectorSums(objects=0, empty=12)
    assert sector_range_errors(far, with_box(road, HORIZON_ROWS, AHEAD, 33.0), SPEC, HORIZON).phantom == 1
    assert sector_range_errors(far, with_box(road, HORIZON_ROWS, AHEAD, 42.0), SPEC, HORIZON).phantom == 0


def test_the_nearest_return_of_a_sector_counts():
    road = flat_road()
    truth = with_box(with_box(road, HORIZON_ROWS, slice(475, 480), 10.0), HORIZON_ROWS, slice(540, 545), 30.0)
    model = with_box(with_box(road, HORIZON_ROWS, slice(475, 480), 35.0), HORIZON_ROWS, slice(540, 545), 12.0)
    # one sector, two objects: the nearest one is read (10 m), the row's nearest is 12 m
    expected = SectorSums(errors_m=(2.0,), objects=1, empty=11, close=1, close_off=1)
    assert sector_range_errors(truth, model, SPEC, HORIZON) == expected
    left = with_box(truth, slice(12, 14), slice(250, 260), 6.0)  # +90 deg, on two low beams
    sums = lidar_decisions(left, road, SPEC)
    assert sums.sectors["horizon"] == SectorSums(objects=1, missed=1, empty=11, close=1, close_off=1)
    assert sums.sectors["low"] == SectorSums(objects=1, missed=1, empty=11, close=1, close_off=1)
    assert sums.sectors["all"] == SectorSums(objects=2, missed=2, empty=10, close=2, close_off=2)


# -------------------------------------------------------------------------------- FRONT view

H, W = 64, 112
# A FRONT camera whose numbers work out by hand: f = 100 px, principal point (56, 32), optical axis
# straight ahead, 1.575 m above the road (LiDAR at 1.84 m, camera 0.265 m below it). A pixel row
# whose centre lies dv below the principal point sees the road 157.5 / dv m ahead.
CAMERA = CameraSpec(
    name="FRONT",
    K=np.array([[100.0, 0.0, 56.0], [0.0, 100.0, 32.0], [0.0, 0.0, 1.0]]),
    R=np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
    t=np.array([0.0, 0.0, -0.265]),
    width=W,
    height=H,
)
MOUNT = 1.84


def test_flat_road_projection_of_pixels():
    x, y = road_points(CAMERA, MOUNT, 56.0, 63.5).T  # row 63's centre: dv = 31.5
    assert x == pytest.approx(5.0) and y == pytest.approx(0.0)
    (x, y), (x2, y2) = road_points(CAMERA, MOUNT, np.array([95.5, 16.5]), np.array([49.5, 49.5]))
    assert x == pytest.approx(9.0) and y == pytest.approx(-39.5 * 9.0 / 100)  # right of the axis: y < 0
    assert x2 == pytest.approx(9.0) and y2 == pytest.approx(39.5 * 9.0 / 100)
    assert np.isnan(road_points(CAMERA, MOUNT, 56.0, 32.0)).all()  # the horizon
    assert np.isnan(road_points(CAMERA, MOUNT, 56.0, 20.5)).all()  # the sky


def _classes(*blobs, value=VEHICLE):
    out = np.zeros((H, W), np.uint8)
    for rows, cols in blobs:
        out[rows, cols] = value
    return out


def test_the_lead_is_the_largest_vehicle_blob_in_the_central_third():
    # Rows 40-47, columns 50-61: 96 pixels; a bigger blob outside columns 37..74 does not count.
    classes = _classes((slice(40, 48), slice(50, 62)), (slice(30, 60), slice(0, 30)))
    assert lead_vehicle(classes) == LeadVehicle(bottom_row=47, centre_col=55.5, pixels=96)
    assert lead_vehicle(_classes((slice(40, 42), slice(50, 51)))) is None  # 2 pixels: speckle
    assert lead_vehicle(np.zeros((H, W), np.uint8)) is None
    # A blob straddling the third's edge counts with its pixels inside it (columns 37-39).
    assert lead_vehicle(_classes((slice(40, 42), slice(30, 40)))) == LeadVehicle(41, 38.0, 6)
    # Equal sizes: the nearer (lower) one.
    two = _classes((slice(34, 36), slice(40, 42)), (slice(50, 52), slice(60, 62)))
    assert lead_vehicle(two).bottom_row == 51
    # 157.5 / (47.5 - 32) = 10.16 m on the flat road, at the blob's centre column 55.5 + 0.5 = 56
    assert LeadVehicle(47, 55.5, 96).range_m(CAMERA, MOUNT) == pytest.approx(157.5 / 15.5)
    assert LeadVehicle(31, 55.5, 96).range_m(CAMERA, MOUNT) == np.inf  # above the horizon


def test_lead_errors_in_pixels_and_metres():
    truth = _classes((slice(44, 48), slice(50, 62)))  # bottom row 47: 10.16 m
    model = _classes((slice(33, 37), slice(52, 64)))  # bottom row 36: 157.5 / 4.5 = 35 m, 2 columns right
    sums = lead_errors(truth, model, CAMERA, MOUNT)
    assert sums.bottom_row_errors_px == (11.0,) and sums.centre_col_errors_px == (2.0,)
    # the row's lead stands 35 m ahead and 2 x 35 / 100 = 0.7 m right of the axis
    assert sums.range_errors_m == pytest.approx((np.hypot(35.0, 0.7) - 157.5 / 15.5,))
    assert (sums.leads, sums.missed, sums.near_leads, sums.near_farther, sums.near_missed) == (1, 0, 1, 1, 0)
    assert lead_errors(truth, truth, CAMERA, MOUNT) == LeadSums(
        bottom_row_errors_px=(0.0,), centre_col_errors_px=(0.0,), range_errors_m=(0.0,), leads=1, near_leads=1
    )
    empty = np.zeros((H, W), np.uint8)
    assert lead_errors(truth, empty, CAMERA, MOUNT) == LeadSums(leads=1, missed=1, near_leads=1, near_missed=1)
    assert lead_errors(empty, truth, CAMERA, MOUNT) == LeadSums(no_lead=1, phantom=1)
    floating = _classes((slice(20, 24), slice(50, 62)))  # the row's lead above the horizon: farther
    assert lead_errors(truth, floating, CAMERA, MOUNT).near_farther == 1
    assert lead_errors(truth, floating, CAMERA, MOUNT).range_errors_m == ()
    far = _classes((slice(30, 35), slice(50, 62)))  # bottom row 34: 63 m, not a near lead
    assert lead_errors(far, far, CAMERA, MOUNT) == LeadSums((0.0,), (0.0,), leads=1)


def test_lane_markings_left_and_right_at_the_bottom():
    # Bottom quarter: rows 48-63. Row 63 sees the road 5 m ahead, row 49 9 m ahead (157.5 / 17.5).
    # Right: column 95 at 5 m (-1.975 m) and column 78 at 9 m (-2.025 m); left: 16 and 33, mirrored.
    right = [(63, 95), (49, 78)]
    left = [(63, 16), (49, 33), (63, 5)]  # column 5 is a marking farther out: the nearest counts
    classes = np.zeros((H, W), np.uint8)
    for r, c in right + left:
        classes[r, c] = MARKING
    classes[20, 60] = MARKING  # above the bottom rows: not read
    assert lane_marking_offsets(classes, CAMERA, MOUNT) == pytest.approx([2.0, -2.0])
    one_row = classes.copy()
    one_row[49, 78] = 0  # the right marking in one row only: speckle
    offsets = lane_marking_offsets(one_row, CAMERA, MOUNT)
    assert offsets[0] == pytest.approx(2.0) and np.isnan(offsets[1])

    model = np.zeros((H, W), np.uint8)
    for r, c in [(63, 105), (49, 84)]:  # right only: 5 m x -0.495 and 9 m x -0.285
        model[r, c] = MARKING
    sums = lane_errors(classes, model, CAMERA, MOUNT)
    assert sums.errors_m == pytest.approx((((2.475 + 2.565) / 2) - 2.0,))
    assert (sums.markings, sums.missed) == (2, 1)
    assert lane_errors(model, classes, CAMERA, MOUNT).markings == 1  # the row's extra marking is not scored
    assert lane_errors(np.zeros((H, W), np.uint8), classes, CAMERA, MOUNT) == LaneSums()


# ------------------------------------------------------------------------ pooled, in the report


def _clip_decisions() -> ClipDecisions:
    road = flat_road()
    truth = with_box(road, HORIZON_ROWS, AHEAD, 10.0)
    lead_truth = _classes((slice(44, 48), slice(50, 62)))
    second0 = lidar_decisions(truth, with_box(road, HORIZON_ROWS, AHEAD, 28.0), SPEC) + camera_decisions(
        lead_truth, lead_truth, CAMERA, MOUNT
    )
    second1 = lidar_decisions(truth, truth, SPEC) + lidar_decisions(truth, road, SPEC)
    return ClipDecisions(second0 + second1, (second0, second1))


def test_readings_pool_over_frames_and_seconds():
    clip = _clip_decisions()
    horizon = clip.overall.sectors["horizon"]
    expected = SectorSums(errors_m=(18.0, 0.0), objects=3, farther=1, missed=1, empty=33, close=3, close_off=2)
    assert horizon == expected
    figures = decision_figures(clip.overall)
    h = figures.sectors["horizon"]
    assert (h.objects, h.error_p50_m, h.error_p95_m) == (3, 9.0, pytest.approx(17.1))  # 0 + 0.95 x 18
    assert h.farther_or_missed == pytest.approx(2 / 3) and h.missed == pytest.approx(1 / 3) and h.phantom == 0.0
    assert figures.sectors["low"].objects == 0 and figures.sectors["low"].error_p50_m is None
    assert figures.lead.leads == 1 and figures.lead.bottom_row_p50_px == 0.0 and figures.lead.missed == 0.0
    assert figures.lanes.markings == 0 and figures.lanes.missed is None
    short = ClipDecisions(clip.per_second[0], clip.per_second[:1])
    seconds = pool_seconds([clip, short])
    assert seconds[0].sectors["horizon"].objects == 2 and seconds[1].sectors["horizon"].objects == 2
    assert DecisionSums() + clip.overall == clip.overall


def test_the_report_shows_what_a_policy_reads_per_row():
    from tests.test_eval_report_units import _clip

    clip = replace(_clip("a", [20.0] * 4), decisions=_clip_decisions())
    row = row_scores([clip], ReportConfig())
    assert isinstance(row.decisions, DecisionScores) and len(row.decisions.per_second) == 2
    assert row.decisions.per_second[1].sectors["horizon"].missed == 0.5
    assert row_scores([_clip("b", [20.0] * 4)], ReportConfig()).decisions is None  # nothing read
    data = json.loads(json.dumps(row.to_json()))
    assert RowScores.from_json(data) == row and data["decisions"]["overall"]["sectors"]["horizon"]["objects"] == 3
    seeded = average_seeds([row, row])
    assert seeded.decisions == row.decisions and seeded.spread.decisions.overall.sectors["horizon"].error_p50_m == 0.0
    assert RowScores.from_json(json.loads(json.dumps(seeded.to_json()))) == seeded

    md = format_markdown(Report({"oracle": row, "bare": RowScores()}, clips=("a",)))
    assert "### What a policy reads (the row's sensors against the recording's)" in md
    assert "| oracle | horizon | 3 | 9.00 / 17.10 | 0.667 | 0.333 | 0.000 |" in md
    assert "| oracle | low | 0 | n/a / n/a | n/a | n/a | 0.000 |" in md  # no object, 36 empty sectors
    assert "| oracle | 1 | 0.000 | 0.0 / 0.0 | 0.0 / 0.0 | 1 | 0.00 / 0.00 | 0.000 | n/a | 0 | n/a / n/a | n/a |" in md
    assert "| oracle | LiDAR horizon: farther or missed | 1.00 | 0.50 |" in md
    assert "| bare |" not in md.split("### What a policy reads")[1]  # a row without readings
    assert "What a policy reads" not in format_markdown(Report({"bare": RowScores()}, clips=()))


# ------------------------------------------------------------------ on a recorded clip, end to end


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    from m4world_env.evalset import EvalsetConfig, record_evalset
    from world_model.data import read_clip

    root = tmp_path_factory.mktemp("evalset")
    cfg = EvalsetConfig(scenarios=("stopped_vehicle_snow",), episodes_per_scenario=1, short_duration=2.0,
                        grid_weathers=(), grid_times=(), long_scenarios=(), base_seed=7200)  # fmt: skip
    return [read_clip(root, e["name"]) for e in record_evalset(root, cfg, progress=False)]


def test_the_report_reads_a_recorded_clip(clips):
    """The recording against itself reads no error; without its objects every object is missed; with
    every object return pushed 18 m away, every object on the horizon beams is farther."""
    from world_model.eval import Generated, evaluate_rows, load_default_judge, oracle_row
    from world_model.eval.report import road_only_row

    def pushed(clip):
        lidar = np.asarray(clip.lidar, np.float32).copy()
        for f, frame in enumerate(clip.frames):
            lidar[f][non_ground_returns(lidar[f], frame.lidar)] += 18.0
        return Generated(np.asarray(clip.cameras), lidar)

    cfg = ReportConfig(frame_stride=10, clip_window=5, lidar_stride=10, chamfer_max_points=512, scene_frame_stride=5)
    rows = {"oracle": oracle_row, "road_only": road_only_row, "pushed": pushed}
    report = evaluate_rows(rows, clips, load_default_judge(), cfg)
    oracle, road_only, far = (report.rows[r].decisions.overall for r in rows)
    horizon = oracle.sectors["horizon"]
    assert horizon.objects > 0 and horizon.error_p95_m == 0.0 and horizon.farther_or_missed == 0.0
    assert oracle.lead.leads > 0 and oracle.lead.bottom_row_p95_px == 0.0 and oracle.lead.missed == 0.0
    assert oracle.lanes.markings == 0 or oracle.lanes.error_p95_m == 0.0
    assert all(b.missed == 1.0 for b in road_only.sectors.values() if b.objects)
    assert far.sectors["horizon"].farther_or_missed == 1.0 and far.sectors["horizon"].error_p50_m >= 17.99
    assert far.lead == oracle.lead  # the same camera frames
    assert "| pushed | horizon |" in format_markdown(report)
