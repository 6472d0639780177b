"""The report's scene IoU and road LiDAR error: a segmenter that sees the recording's labels scores
1 on the classes in view, one that sees only background scores 0 on the road, the quality bar
compares a row's every second with the autoencoder row's, and the markdown shows it per second."""

import json

import numpy as np
import pytest

from m4world_env.evalset import EvalsetConfig, record_evalset
from world_model.data import read_clip
from world_model.eval import Generated, evaluate_rows, format_markdown, load_default_judge, oracle_row
from world_model.eval.report import ReportConfig, RowScores, SceneIoUScores, check_bars, scene_iou_bar
from world_model.eval.scene_iou import scene_labels
from world_model.eval.segmenter import SCENE_CLASSES, SegmenterConfig, SegNet


class LabelLookup:
    """A perfect segmenter for the recorded clips: frames are looked up by their bytes."""

    def __init__(self, clips):
        self.net = SegNet(SegmenterConfig())  # only its weights' digest is read (the cache key)
        self.table = {}
        for clip in clips:
            cams = np.asarray(clip.cameras)
            labels = scene_labels(clip.frames, *cams.shape[2:4])
            for t in range(len(cams)):
                for v in range(cams.shape[1]):
                    self.table[cams[t, v].tobytes()] = labels[t, v]

    def predict(self, images):
        flat = images.reshape(-1, *images.shape[-3:])
        background = np.zeros(images.shape[-3:-1], np.uint8)
        return np.stack([self.table.get(x.tobytes(), background) for x in flat]).reshape(images.shape[:-1])


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    root = tmp_path_factory.mktemp("evalset")
    cfg = EvalsetConfig(
        scenarios=(),
        short_duration=2.0,
        grid_scenarios=("highway_sunny_day",),
        grid_weathers=("sunny",),
        grid_times=("day",),
        long_scenarios=(),
        base_seed=7100,
    )
    return [read_clip(root, e["name"]) for e in record_evalset(root, cfg, progress=False)]


def test_scene_iou_sees_the_road_and_a_row_without_it(clips):
    cfg = ReportConfig(frame_stride=4, clip_window=5, lidar_stride=10, chamfer_max_points=1024, long_window_s=1,
                       scene_frame_stride=2)  # fmt: skip
    rows = {
        "oracle": oracle_row,
        "autoencoder": oracle_row,
        "grey": lambda c: Generated(np.full_like(np.asarray(c.cameras), 128), np.asarray(c.lidar, np.float32)),
    }
    report = evaluate_rows(rows, clips, load_default_judge(), cfg, segmenter=LabelLookup(clips))
    oracle, grey, ceiling = (report.rows[r] for r in ("oracle", "grey", "autoencoder"))
    assert oracle.table1.road_iou == 1.0 and oracle.table1.vehicle_iou == 1.0
    assert grey.table1.road_iou == 0.0  # all background: no road pixel predicted
    seconds = int(clips[0].num_frames // clips[0].fps)
    assert len(oracle.scene_iou.per_second) == seconds
    assert set(oracle.scene_iou.overall) == set(SCENE_CLASSES)
    assert oracle.scene_iou.last_window_long_clips["road"] == 1.0  # 2 s clips >= 2 x the 1 s window
    assert oracle.table1.lidar_road_mae_m == 0.0 and grey.table1.lidar_road_mae_m == 0.0
    assert scene_iou_bar(oracle, ceiling, "road", 0.8)[1] is True
    measured, ok = scene_iou_bar(grey, ceiling, "road", 0.8)
    assert ok is False and measured.startswith("worst 0.000 x")
    assert "### Scene IoU per second" in format_markdown(report)
    assert RowScores.from_json(json.loads(json.dumps(grey.to_json()))) == grey  # report.json round trip
    bars = {c.bar: c for c in check_bars(report, "grey")}
    assert bars["road IoU ≥ 0.8 x autoencoder at every second of every clip"].met is False


def test_the_scene_iou_bar_is_not_measured_without_an_autoencoder_row():
    scores = RowScores(scene_iou=SceneIoUScores(overall={}, per_second=(), last_window_long_clips=None, per_clip=()))
    assert scene_iou_bar(scores, None, "road", 0.8) == ("", None)
    assert scene_iou_bar(RowScores(), scores, "road", 0.8) == ("", None)
