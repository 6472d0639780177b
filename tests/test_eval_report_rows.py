"""The report's optional rows: the geometry-only baseline, the bidirectional teacher, refresh variants."""

import json
from dataclasses import replace

import pytest
import torch

from m4world_env.cli import main
from world_model.eval.report import StudentStreaming
from world_model.eval.report.rows import world_model_row
from world_model.model import MultiViewDiT, get_preset
from world_model.rollout.runtime import load_world_model, save_untrained_bundle
from world_model.streaming import StreamingConfig, StreamingConfigError
from world_model.train.checkpoint import export_weights


def test_geometry_only_config_ignores_object_descriptions():
    cfg = get_preset("tiny", geometry_only=True)
    assert not cfg.control.object_descriptions and get_preset("tiny").control.object_descriptions
    from tests.model_fixtures import tiny_conditions

    torch.manual_seed(0)
    full = MultiViewDiT(get_preset("tiny")).tokenizer
    geo = MultiViewDiT(cfg).tokenizer
    geo.load_state_dict(full.state_dict())
    cond = tiny_conditions(cfg, 2, batch=1)
    assert cond.obj_has_text.any()
    other = replace(cond, obj_text=torch.randn_like(cond.obj_text))
    # the geometry-only tokens do not see a changed text description; the full model's do
    assert torch.equal(geo.object_tokens(cond), geo.object_tokens(other))
    assert not torch.equal(full.object_tokens(cond), full.object_tokens(other))


@pytest.mark.slow
def test_report_with_geometry_only_and_teacher_rows(tiny_bundle, tmp_path):
    clips = tmp_path / "eval"
    args = ["record", "--scenario", "merge_cut_in", "--episodes", "1", "--duration", "0.6", "--out", str(clips)]
    assert main([*args, "--height", "16", "--width", "32", "--seed", "1000"]) == 0
    baseline = save_untrained_bundle(tmp_path / "geo", geometry_only=True)
    assert not load_world_model(baseline).cfg.control.object_descriptions
    cfg = get_preset("tiny")
    teacher = tmp_path / "run" / "teacher" / "model"
    export_weights(teacher, MultiViewDiT(cfg).state_dict(), {"stage": "teacher", "model_config": cfg.to_dict()})
    out = tmp_path / "report"
    cmd = ["eval", "--report", "--evalset", str(clips), "--checkpoint", str(tiny_bundle), "--out", str(out)]
    assert main([*cmd, "--baseline", str(baseline), "--teacher", str(teacher)]) == 0
    rows = json.loads((out / "report.json").read_text())["rows"]
    assert list(rows) == [
        "oracle",
        "autoencoder",
        "road_only",
        "first_frame",
        "geometry_only",
        "student",
        "student_no_refresh",
        "teacher",
    ]
    n = rows["oracle"]["answers"]
    assert all(r["answers"] == n for r in rows.values())  # every row answered the same questions
    # The teacher's independent 3-frame windows: a jump into each window start, scored against the recording.
    assert rows["teacher"]["table1"]["chunk_jump_cameras"] > 0 and rows["teacher"]["table1"]["chunk_jump_lidar"] > 0
    assert all(v > 0 for v in rows["teacher"]["chunk_jumps"]["lidar"].values())


def test_student_rows_stream_with_the_refresh_they_are_named_for(tiny_bundle):
    wm = load_world_model(tiny_bundle)

    def streamed(row: StudentStreaming, bundle: StreamingConfig = wm.streaming) -> StreamingConfig:
        return world_model_row(wm, streaming=row.streaming(bundle)).wm.student_cfg.streaming

    # The headline row: the bundle's streaming.json (the last two steps refresh, one sink frame).
    assert world_model_row(wm).wm.student_cfg.streaming == streamed(StudentStreaming()) == StreamingConfig()
    assert streamed(StudentStreaming(refresh_steps=(2, 3))).resolved_refresh_steps() == (2, 3)
    assert streamed(StudentStreaming(context_refresh=False)).resolved_refresh_steps() == ()
    # A bundle streaming without refresh still gets the partial-refresh row it is asked for.
    off = replace(wm.streaming, context_refresh=False)
    assert streamed(StudentStreaming(refresh_steps=(0,)), off).resolved_refresh_steps() == (0,)
    sink = streamed(StudentStreaming(refresh_steps=(2, 3), sink_frames=0))
    assert sink.sink_frames == 0 and sink.resolved_refresh_steps() == (2, 3)
    with pytest.raises(StreamingConfigError, match=r"--refresh-steps \[4\] names no step of the 4 denoising steps"):
        StudentStreaming(refresh_steps=(4,)).streaming(wm.streaming)
