"""m4world bench segmenter with a small untrained segmenter on a short recording."""

import json

import numpy as np
import torch

from m4world_env.bench.segmenter import front_readings, main
from m4world_env.cli import main as cli
from world_model.data import read_clip
from world_model.eval.decisions import FRONT_VIEW
from world_model.eval.segmenter import SCENE_CLASSES, Segmenter, SegmenterConfig, SegNet
from world_model.eval.segmenter_data import cached_scene_labels, clip_refs


def test_bench_reports_iou_per_class_and_ms_per_frame(tmp_path, capsys):
    data = tmp_path / "heldout"
    args = ["record", "--scenario", "highway_sunny_day", "--episodes", "1", "--duration", "1", "--seed", "500"]
    assert cli([*args, "--out", str(data)]) == 0
    torch.manual_seed(0)
    Segmenter(SegNet(SegmenterConfig(channels=(4, 8), head_channels=4))).save(tmp_path / "seg")
    out = tmp_path / "bench"
    cmd = ["--data", str(data), "--segmenter", str(tmp_path / "seg"), "--frames", "2", "--repeats", "1"]
    assert main([*cmd, "--stride", "5", "--out", str(out)]) == 0
    result = json.loads((out / "bench_segmenter.json").read_text())
    row = result["datasets"]["heldout"]
    assert row["clips"] == 1 and row["views"] == 3 * 6  # frames 0, 5, 10 of 11, six cameras
    assert set(row["iou"]) == set(SCENE_CLASSES)
    assert all(v is None or 0.0 <= v <= 1.0 for v in row["iou"].values())
    front = row["front"]
    assert front["leads"] + front["markings"] > 0  # the recording's FRONT shows the road ahead
    shares = ("lead_missed", "lead_within_px", "lead_phantom", "lane_missed")
    assert all(front[k] is None or 0.0 <= front[k] <= 1.0 for k in shares)
    assert result["ms_per_frame"] > 0 and result["frame_shape"] == [6, 64, 112, 3]
    assert "ms per 6-view frame" in capsys.readouterr().out


def test_front_readings_of_a_segmenter_that_reads_the_labels_are_exact(tmp_path):
    data = tmp_path / "rec"
    args = ["record", "--scenario", "highway_sunny_day", "--episodes", "1", "--duration", "1", "--seed", "501"]
    assert cli([*args, "--out", str(data)]) == 0
    refs = clip_refs([str(data)])
    clip = read_clip(refs[0].root, refs[0].name)
    labels = cached_scene_labels(clip, tmp_path / "labels")
    front = [c.name for c in clip.frames[0].rig.cameras].index(FRONT_VIEW)
    by_image = {np.asarray(clip.cameras[f, front]).tobytes(): labels[f, front] for f in range(clip.num_frames)}

    class ReadsLabels:
        def predict(self, images: np.ndarray) -> np.ndarray:
            return np.stack([by_image[im.tobytes()] for im in images])

    readings = front_readings(ReadsLabels(), refs, tmp_path / "labels", stride=2)
    assert readings["leads"] > 0  # a car ahead in this episode's first second
    assert readings["lead_within_px"] == 1.0 and readings["lead_bottom_row_p95_px"] == 0.0
    assert readings["lead_missed"] == 0.0 and readings["lane_missed"] in (None, 0.0)
