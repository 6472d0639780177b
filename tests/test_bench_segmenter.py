"""m4world bench segmenter with a small untrained segmenter on a short recording."""

import json

import torch

from m4world_env.bench.segmenter import main
from m4world_env.cli import main as cli
from world_model.eval.segmenter import SCENE_CLASSES, Segmenter, SegmenterConfig, SegNet


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
    assert result["ms_per_frame"] > 0 and result["frame_shape"] == [6, 64, 112, 3]
    assert "ms per 6-view frame" in capsys.readouterr().out
