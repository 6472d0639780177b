"""The report's pure pieces on hand-made inputs: judge answers to yes-frequencies, clips pooled
into a row, report.json round trips, cache keys, row lineup names and the markdown tables."""

import copy
import json
from dataclasses import fields, replace

import numpy as np
import pytest
import torch

from world_model.eval.metrics import ChangeSums, ConfusionSums, JumpSums
from world_model.eval.questions import QUESTION_TYPES
from world_model.eval.report import (
    ClipChunkJumps,
    GenerationScores,
    JumpRatios,
    LongHorizon,
    Report,
    ReportConfig,
    ReportRequest,
    RowScores,
    StudentStreaming,
    WindowFrechet,
    YesFrequencies,
    format_markdown,
)
from world_model.eval.report.cache import row_cache_key
from world_model.eval.report.clip_scores import ClipScores, StreamPair
from world_model.eval.report.judging import Answer, per_category, yes_frequencies
from world_model.eval.report.lineup import RowIdentity
from world_model.eval.report.row_scores import row_scores
from world_model.eval.scene_iou import SceneIoU
from world_model.eval.segmenter import SCENE_CLASSES, Segmenter, SegmenterConfig, SegNet


def test_yes_frequencies_and_per_category():
    answers = [
        Answer("weather", True, None),
        Answer("weather", False, None),
        Answer("existence", True, "car"),
        Answer("existence", True, "car"),
        Answer("existence", False, "bus"),
    ]
    freq = yes_frequencies(answers)
    assert freq.weather == 0.5 and freq.of("existence") == pytest.approx(2 / 3)
    assert freq.clarity is None
    assert per_category(answers) == {"existence": {"bus": 0.0, "car": 1.0}}
    assert tuple(f.name for f in fields(YesFrequencies)) == QUESTION_TYPES  # Table 2's columns, in order
    with pytest.raises(ValueError, match="unknown question type 'colour'"):
        freq.of("colour")


def _clip(name, psnrs, lidar_mae=None, jumps=None, answers=(), moved=1.0):
    n = len(psnrs)
    motion = {"cameras": StreamPair(ChangeSums(moved * n, n), ChangeSums(float(n), n))}
    return ClipScores(
        clip=name,
        fps=2.0,
        psnr_per_frame=np.array(psnrs, float),
        ssim_scored=np.full((n + 1) // 2, 0.5),
        lidar_mae_per_frame=None if lidar_mae is None else np.array(lidar_mae, float),
        chamfers=(),
        object_psnrs=(30.0,),
        object_maes=(),
        road_maes=(0.5, 1.5),
        motion=motion,
        jumps=jumps,
        answers=tuple(answers),
        features=None,
        long_horizon=None,
        scene_iou=None,
    )


def test_row_scores_pool_frames_sums_and_answers_over_clips():
    cfg = ReportConfig(frame_stride=2, lidar_stride=2)
    jumps = {"cameras": StreamPair(JumpSums(6.0, 2, 3.0, 3), JumpSums(2.0, 2, 2.0, 2))}  # 3 / 1 vs 1 / 1
    a = _clip("a", [10, 99, 20, 99], lidar_mae=[1, 5, 3, 5], jumps=jumps, answers=[Answer("weather", True, None)])
    b = _clip("b", [40, 99], answers=[Answer("weather", False, None)] * 3, moved=0.0)
    row = row_scores([a, b], cfg)
    t1 = row.table1
    assert t1.psnr_db == pytest.approx((10 + 20 + 40) / 3)  # every 2nd frame of every clip, pooled
    assert t1.ssim == 0.5 and t1.object_psnr_db == 30.0 and t1.lidar_object_mae_m is None
    assert t1.lidar_road_mae_m == 1.0 and t1.road_iou is None and row.scene_iou is None  # clips without scene IoU
    assert t1.lidar_range_mae_m == pytest.approx(2.0)  # frames 0 and 2 of the clip with LiDAR
    assert t1.lidar_range_mae_first_s_m == pytest.approx(3.0)  # its first second: 2 frames at 2 fps
    assert t1.lidar_chamfer_m is None and t1.frechet_judge_frame is None  # no LiDAR points, no judge features
    assert t1.motion_cameras == pytest.approx(4 / 6) and t1.motion_lidar is None  # sums add: 4 of 6 frames move
    assert t1.chunk_jump_cameras == pytest.approx(3.0) and t1.chunk_jump_lidar is None
    assert row.chunk_jumps == {"cameras": JumpRatios(3.0, 1.0)}
    assert row.chunk_jumps_per_clip == (ClipChunkJumps("a", 3.0, None),)  # only the clip generated in passes
    assert row.table2.weather == 0.25 and row.answers == 4 and row.per_view == {}
    with pytest.raises(ValueError, match="at least one clip"):
        row_scores([], cfg)


def _long(name, frechet=True, lidar=True):
    return LongHorizon(
        clip=name,
        seconds=3,
        psnr_per_second=(30.0, 28.0, 27.0),
        ratio_last_first=0.9,
        frechet=WindowFrechet(2.0, 3.0, 1.5) if frechet else None,
        lidar_mae_per_second=(0.5, 0.6, 0.7) if lidar else None,
        motion_cameras=0.8,
        motion_lidar=None,
    )


def _hand_made_report():
    student = RowScores(
        table1=GenerationScores(psnr_db=21.5, ssim=0.61, chunk_jump_cameras=1.25),
        table2=YesFrequencies(weather=0.75, existence=0.5),
        chunk_jumps={"cameras": JumpRatios(2.5, 2.0)},
        chunk_jumps_per_clip=(ClipChunkJumps("long_a", 1.5, None), ClipChunkJumps("long_b", 1.0, None)),
        per_category={"existence": {"car": 0.5}},
        per_view={"weather": (1.0, 0.5)},
        answers=8,
        long_horizon=(_long("long_a"), _long("long_b", frechet=False, lidar=False)),
    )
    oracle = RowScores(table1=GenerationScores(psnr_db=100.0, ssim=1.0), table2=YesFrequencies(weather=1.0))
    return Report({"oracle": oracle, "student": student}, clips=("long_a", "long_b"), config=ReportConfig())


def test_report_json_round_trips_with_the_report_keys():
    report = _hand_made_report()
    data = json.loads(json.dumps(report.to_json()))
    assert Report.from_json(data) == report
    assert list(data) == ["rows", "clips", "config"] and data["config"]["long_window_s"] == 10
    row = data["rows"]["student"]
    assert list(row) == ["table1", "chunk_jumps", "chunk_jumps_per_clip", "table2", "per_category", "per_view",
                         "answers", "long_horizon", "scene_iou"]  # fmt: skip
    assert list(row["table1"])[:4] == ["frechet_judge_frame", "frechet_judge_clip", "psnr_db", "ssim"]
    assert row["chunk_jumps"] == {"cameras": {"generated": 2.5, "recording": 2.0}}
    full, bare = row["long_horizon"]
    assert full["frechet_ratio_last_first"] == 1.5 and full["lidar_mae_per_second"] == [0.5, 0.6, 0.7]
    assert "frechet_judge_frame_first" not in bare and "lidar_mae_per_second" not in bare  # not measured: no key
    del row["table2"]
    with pytest.raises(ValueError, match="report row has no 'table2'"):
        Report.from_json(data)


def test_markdown_of_a_hand_made_report():
    md = format_markdown(_hand_made_report())
    student_table1 = "| student | n/a | n/a | 21.500 | 0.610 | " + "n/a | " * 9 + "1.250 | n/a | n/a | n/a |"
    assert student_table1 in md
    assert "| oracle | 1.000 | n/a | n/a |" in md  # Table 2: weather, time_of_day, existence, ...
    assert "| student | car |" not in md and "| student | 0.500 |" in md  # existence per category
    assert "| student | weather | 1.000 | 0.500 |" in md  # per camera view
    assert "### Long horizon: last 10 s vs first 10 s of each long clip" in md
    assert "| student | long_a | 3.000 | 0.900 | 2.000 | 3.000 | 1.500 | 0.800 | n/a |" in md
    assert "| student | long_b | 3.000 | 0.900 | n/a | n/a | n/a | 0.800 | n/a |" in md
    assert "| student | 2 | 1.250 (1.000-1.500) | n/a |" in md  # chunk jumps per clip: median (min-max)
    assert "### Quality bars (student)" in md and "| weather ≥ 0.85 x oracle | 0.750 / 1.000 = 0.750 x | missed" in md


class _Judge:  # a stand-in backend: its identity in a cache key is its class name
    pass


_SEGMENTER = Segmenter(SegNet(SegmenterConfig(channels=(4,), head_channels=2)))  # its weights' digest is keyed


def test_cache_key_changes_with_every_streaming_setting(tmp_path):
    (tmp_path / "manifest.json").write_text("{}")
    ident = RowIdentity(ReportRequest(checkpoint=str(tmp_path)), dtype="float32")
    settings = [
        StudentStreaming(),
        StudentStreaming(context_refresh=False),
        StudentStreaming(refresh_steps=(0,)),
        StudentStreaming(refresh_steps=(1, 3)),
        StudentStreaming(sink_frames=1),
        StudentStreaming(refresh_steps=(0,), sink_frames=1),
        StudentStreaming(refresh_steps=(0,), sink_frames=2),
        StudentStreaming(sink_frames=0),
        StudentStreaming(refresh_steps="all"),
    ]
    cfg = ReportConfig()

    def key(row_id, config=cfg):
        return row_cache_key(row_id, [], config, _Judge(), _SEGMENTER)

    keys = {key(ident.student(str(tmp_path), s)) for s in settings}
    assert len(keys) == len(settings)
    plain = ident.student(str(tmp_path))
    assert key(plain) == key(plain) and key(plain) != key(plain, replace(cfg, frame_stride=3))
    window = RowIdentity(ReportRequest(checkpoint=str(tmp_path), context_frames=4), dtype="float32")
    assert key(window.student(str(tmp_path))) != key(plain)
    assert key(RowIdentity(ident.request, dtype="bfloat16").student(str(tmp_path))) != key(plain)
    assert key(RowIdentity(replace(ident.request, seed=1), "float32").student(str(tmp_path))) != key(plain)
    (tmp_path / "manifest.json").write_text('{"other": "weights"}')
    assert key(ident.student(str(tmp_path))) != key(plain)  # another bundle
    retrained = copy.deepcopy(_SEGMENTER)
    with torch.no_grad():
        next(retrained.net.parameters()).add_(0.5)
    assert row_cache_key(plain, [], cfg, _Judge(), retrained) != key(plain)  # another segmenter


def test_lineup_names_and_request_checks():
    request = ReportRequest(refresh_steps=((0,), (1, 3)), sink_frames=(1, 0))
    names = [s.row_name for s in request.student_streamings()]
    assert names == ["student", "student_no_refresh", "student_refresh_0", "student_refresh_1_3", "student_sink_1",
                     "student_refresh_0_sink_1", "student_refresh_1_3_sink_1", "student_sink_0",
                     "student_refresh_0_sink_0", "student_refresh_1_3_sink_0"]  # fmt: skip
    assert StudentStreaming(refresh_steps="all").row_name == "student_refresh_all"
    with pytest.raises(ValueError, match=r"--sink-frames must be an integer in \[0, 64\], got 65"):
        ReportRequest(sink_frames=(65,))
    with pytest.raises(ValueError, match=r"--refresh-steps must be 'all' or a non-empty list .*, got \[\]"):
        ReportRequest(refresh_steps=((),))
    with pytest.raises(ValueError, match="seeds must be >= 1"):
        ReportRequest(seeds=0)
    with pytest.raises(ValueError, match="dtype must be one of"):
        ReportRequest(dtype="fp8")
    with pytest.raises(ValueError, match="ReportConfig.clip_window must be >= 2"):
        ReportConfig(clip_window=1)


def _road_seconds(*hits):
    """Per-second sums where the road (class 1) is labelled on 4 pixels and predicted on ``hit`` of them."""
    classes = len(SCENE_CLASSES)
    out = []
    for hit in hits:
        road = np.zeros(classes, np.int64)
        road[SCENE_CLASSES.index("road")] = 1
        out.append(ConfusionSums(road * hit, road * hit, road * 4))
    return tuple(out)


def test_scene_iou_pools_clips_of_any_length_per_second():
    short, long = _road_seconds(4, 2), _road_seconds(4, 0, 0)  # a 2 s and a 3 s clip: last windows of 2 and 3 s
    zero = ConfusionSums.zeros(len(SCENE_CLASSES))
    a = replace(_clip("a", [20.0] * 4), scene_iou=SceneIoU(short, sum(short, zero), 2))
    b = replace(_clip("b", [20.0] * 6), scene_iou=SceneIoU(long, sum(long, zero), 3))
    scene = row_scores([a, b], ReportConfig()).scene_iou
    assert [s["road"] for s in scene.per_second] == [1.0, 2 / 8, 0.0]  # second 2: only the 3 s clip
    assert scene.overall["road"] == pytest.approx(10 / 20) and scene.last_window_long_clips is None
    assert [c.clip for c in scene.per_clip] == ["a", "b"] and scene.per_clip[1].per_second[1]["road"] == 0.0
