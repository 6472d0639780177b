"""m4world bench front_reads, small: the lane finder's lines are read from pixels, the markings and
the car ahead's bottom edge from the segmenter's classes (the car only within range), a lost line
counts in the median of the rows, a shift of the view shows as its size in px, the ground truth read
against itself is the same pixel and its markings and car ahead where its label map has them, and
the command writes the figures per scenario with the world model (the untrained tiny bundle) fed
the ground truth's actions."""

import json

import numpy as np
import pytest

from m4world_env.bench.front_reads import (
    BAND_ROWS,
    LEAD_RANGE_M,
    MISSING_PX,
    READINGS,
    SEGMENTED_MARKING,
    SEGMENTED_VEHICLE,
    bottom_edge,
    episode,
    figures,
    frame_reads,
    lead_vehicle,
    line_columns,
    lines_apart,
    main,
    marking_columns,
    path_vehicle_columns,
)
from world_model.eval.segmenter import SCENE_CLASSES, load_default_segmenter
from world_model.raster.classes import MARKING, ROAD, SKY, VEHICLE
from world_model.sensors import CameraSpec

H, W = 64, 112
ROAD_GREY, LINE_WHITE, CAR_RED = (90, 90, 90), (235, 235, 235), (200, 30, 30)


def road_view(lines: tuple[int, ...] = (20, 90), car_rows: tuple[int, int] | None = None) -> np.ndarray:
    """A grey road with 2-px white lines starting at ``lines`` in its bottom band, and a red car
    across the view's centre from row ``car_rows[0]`` to ``car_rows[1]`` (inclusive)."""
    image = np.full((H, W, 3), ROAD_GREY, np.uint8)
    for c in lines:
        image[-BAND_ROWS:, c : c + 2] = LINE_WHITE
    if car_rows is not None:
        image[car_rows[0] : car_rows[1] + 1, 46:66] = CAR_RED
    return image


def class_map(car_rows: tuple[int, int] | None, lines: tuple[int, ...], ids: tuple[int, int, int]) -> np.ndarray:
    """The classes of :func:`road_view`, ``ids`` those of the road, a marking and a vehicle."""
    road, marking, vehicle = ids
    classes = np.full((H, W), road, np.int64)
    for c in lines:
        classes[-BAND_ROWS:, c : c + 2] = marking
    if car_rows is not None:
        classes[car_rows[0] : car_rows[1] + 1, 46:66] = vehicle
    return classes


def labels(car_rows: tuple[int, int] | None, lines: tuple[int, ...] = (20, 90)) -> np.ndarray:
    """The label map of :func:`road_view`, its top rows sky."""
    classes = class_map(car_rows, lines, (ROAD, MARKING, VEHICLE))
    classes[:20] = SKY
    return classes


def test_the_lines_are_the_innermost_on_each_side_of_the_centre():
    cols = line_columns(road_view((5, 20, 90, 100)))
    assert cols.shape == (BAND_ROWS, 2) and np.all(cols == (20.5, 90.5))
    assert np.isnan(line_columns(road_view(()))).all()
    assert np.isnan(line_columns(road_view((20,)))[:, 1]).all()


def test_lines_apart_is_the_largest_shift_or_a_missing_line():
    a = line_columns(road_view((20, 90)))
    assert lines_apart(a, a) == 0.0
    assert lines_apart(a, line_columns(road_view((21, 91)))) == 1.0
    assert lines_apart(a, line_columns(road_view((20,)))) == (0.0 + MISSING_PX) / 2  # a side of rows lost
    assert lines_apart(a, line_columns(road_view((20, 90, 100)))) == 0.0  # an outer line is not read
    none = line_columns(road_view(()))
    assert lines_apart(none, none) is None


def test_the_car_ahead_is_the_nearest_vehicle_in_the_path():
    columns, bottom = path_vehicle_columns(labels((30, 40)))
    assert bottom == 40 and columns.min() >= 46 and columns.max() <= 65
    side = labels(None)
    side[30:40, :10] = VEHICLE  # beside the path: not the car ahead
    assert path_vehicle_columns(side) is None


def level_camera(height_px: int = H, focal_px: float = 80.0) -> CameraSpec:
    """A forward camera at the LiDAR's height, looking level (x forward, y left, z up)."""
    k = np.array([[focal_px, 0.0, W / 2], [0.0, focal_px, height_px / 2], [0.0, 0.0, 1.0]])
    r = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return CameraSpec(name="FRONT", K=k, R=r, t=np.zeros(3), width=W, height=height_px)


def test_the_car_ahead_is_read_only_within_range():
    camera, mount = level_camera(), 1.6
    near_row = 32 + 10  # 80 px * 1.6 m / 10.5 px: 12 m ahead
    assert lead_vehicle(labels((30, near_row)), camera, mount)[1] == near_row
    far_row = 32 + int(80 * mount / (LEAD_RANGE_M * 1.5))  # half as far again as the range
    assert lead_vehicle(labels((30, far_row)), camera, mount) is None
    assert lead_vehicle(labels(None), camera, mount) is None


def segments_of(car_rows: tuple[int, int] | None, lines: tuple[int, ...] = (20, 90)) -> np.ndarray:
    """The segmenter's classes of :func:`road_view`: road, its markings, and the car where it is drawn."""
    return class_map(car_rows, lines, (SCENE_CLASSES.index("road"), SEGMENTED_MARKING, SEGMENTED_VEHICLE))


def test_the_markings_are_read_from_the_segments_as_from_a_label_map():
    assert np.all(marking_columns(segments_of(None, (5, 20, 90)), SEGMENTED_MARKING) == (20.5, 90.5))
    assert np.all(marking_columns(labels(None, (20, 90, 100)), MARKING) == (20.5, 90.5))
    assert np.isnan(marking_columns(segments_of(None, ()), SEGMENTED_MARKING)).all()


def test_the_bottom_edge_is_read_from_the_segments_and_a_shift_shows():
    lead = path_vehicle_columns(labels((30, 40)))
    columns, _ = lead
    assert bottom_edge(segments_of((30, 40)), columns) == 40.0
    assert bottom_edge(segments_of(None), columns) is None
    views = np.stack([road_view(car_rows=(30, 40)), road_view((22, 92), car_rows=(30, 42))])
    segments = np.stack([segments_of((30, 40)), segments_of((30, 42), (23, 93))])
    reads = frame_reads(views, labels((30, 40)), segments, lead)
    assert reads == {
        "lines_px": 2.0,
        "lines_truth_vs_label": 0.0,
        "markings_px": 3.0,
        "markings_truth_vs_label": 0.0,
        "edge_px": 2.0,
        "edge_truth_vs_label": 0.0,
        "edge_model_vs_label": 2.0,
    }
    plain = np.stack([road_view()] * 2)
    lost = frame_reads(plain, labels((30, 40)), np.stack([segments_of((30, 40)), segments_of(None, ())]), lead)
    assert lost["edge_px"] == MISSING_PX and lost["markings_px"] == MISSING_PX
    unseen = frame_reads(plain, labels((30, 40)), np.stack([segments_of(None)] * 2), lead)
    assert unseen["edge_px"] is None and unseen["edge_truth_vs_label"] == MISSING_PX
    assert unseen["edge_model_vs_label"] == MISSING_PX
    assert frame_reads(plain, labels(None), np.stack([segments_of(None)] * 2), None)["edge_px"] is None


def test_figures_count_the_frames_within_each_tolerance():
    nothing = {
        "lines_truth_vs_label": None,
        "markings_px": None,
        "markings_truth_vs_label": None,
        "edge_model_vs_label": None,
    }
    reads = [
        {"lines_px": 0.0, "edge_px": 1.0, "edge_truth_vs_label": -1.0, **nothing},
        {"lines_px": 2.0, "edge_px": None, "edge_truth_vs_label": None, **nothing},
        {"lines_px": None, "edge_px": 3.0, "edge_truth_vs_label": 0.0, **nothing},
    ]
    f = figures(reads)
    assert f["lines_px"]["frames"] == 2 and f["lines_px"]["within_1px"] == 0.5 and f["lines_px"]["within_2px"] == 1.0
    assert f["edge_px"]["frames"] == 2 and f["edge_px"]["median_px"] == 2.0
    assert f["edge_truth_vs_label"]["within_1px"] == 1.0
    empty = figures([])["lines_px"]
    assert empty["frames"] == 0 and empty["within_1px"] is None and empty["p95_px"] is None


def test_the_ground_truth_against_itself_reads_the_same_pixels():
    reads = episode("merge_cut_in", 0, 3, {"backend": "procedural"}, load_default_segmenter())
    assert len(reads) == 3
    assert all(r[key] in (0.0, None) for r in reads for key in ("lines_px", "markings_px", "edge_px"))
    assert any(r["lines_px"] == 0.0 for r in reads)
    assert all(r["markings_truth_vs_label"] <= 1 for r in reads)  # the segmenter finds the painted lines
    # A car ahead within range on every frame, its bottom edge segmented where its label map has it.
    assert all(r["edge_px"] == 0.0 and abs(r["edge_truth_vs_label"]) <= 1 for r in reads)
    assert all(r["edge_model_vs_label"] == r["edge_truth_vs_label"] for r in reads)


def test_the_command_writes_each_scenario(tiny_bundle, tmp_path):
    out = tmp_path / "fr.json"
    args = ["--scenarios", "highway_sunny_day", "--seeds", "0", "--steps", "2", "--checkpoint", str(tiny_bundle)]
    assert main([*args, "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["steps"] == 2 and set(result["results"]) == {"highway_sunny_day"}
    assert set(result["results"]["highway_sunny_day"]) == set(READINGS)
    with pytest.raises(SystemExit):
        main(["--scenarios", "no_such_scenario", "--out", str(tmp_path / "x.json")])
