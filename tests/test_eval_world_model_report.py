"""`m4world eval --report` with a world-model bundle (untrained tiny: plumbing, shapes, rows)."""

import json

from m4world_env.cli import main
from tests.cli_status import exit_status


def test_eval_report_rows_for_a_bundle(tiny_bundle, tmp_path, capsys):
    clips = tmp_path / "eval"
    # the tiny preset generates 16x32 views: record the evaluation clips at that resolution
    assert (
        main(
            [
                "record",
                "--scenario",
                "merge_cut_in",
                "--episodes",
                "1",
                "--duration",
                "0.6",
                "--out",
                str(clips),
                "--height",
                "16",
                "--width",
                "32",
                "--seed",
                "1000",
            ]
        )
        == 0
    )
    out = tmp_path / "report"
    only = ["--clips-prefix", "merge_cut_in"]  # the clip's name: all of them
    assert (
        main(["eval", "--report", "--evalset", str(clips), "--checkpoint", str(tiny_bundle), "--out", str(out), *only])
        == 0
    )
    report = json.loads((out / "report.json").read_text())
    assert set(report["rows"]) == {"oracle", "autoencoder", "road_only", "first_frame", "student", "student_no_refresh"}
    oracle, student = report["rows"]["oracle"]["table1"], report["rows"]["student"]["table1"]
    assert oracle["psnr_db"] > student["psnr_db"]  # an untrained model is far from the ground truth
    assert student["lidar_range_mae_m"] > oracle["lidar_range_mae_m"] == 0.0
    # The tiny preset's chunks are single frames: every change crosses a chunk boundary, no ratio.
    assert student["chunk_jump_cameras"] is None and oracle["chunk_jump_cameras"] is None
    assert report["rows"]["autoencoder"]["table1"]["psnr_db"] < oracle["psnr_db"]  # the VAE loses detail
    printed = capsys.readouterr().out
    assert "student_no_refresh" in printed
    assert "### Quality bars (student)" in printed and "| existence ≥ 0.8 x oracle |" in printed
    assert "| visual_fidelity ≥ geometry_only + 0.30 | " in printed and "not measured" in printed  # no baseline
    # Each finished row is kept: a rerun (e.g. adding a --baseline row) reuses them, same numbers.
    kept = sorted(p.stem for p in (out / "rows").iterdir())
    seeds = [f"{row}.seed{k}" for row in ("student", "student_no_refresh") for k in range(3)]  # --seeds' default
    assert kept == ["autoencoder", "first_frame", "oracle", "road_only", *seeds]
    assert report["rows"]["student"]["seeds"] == 3 and "psnr_db" in report["rows"]["student"]["spread"]["table1"]
    assert len(report["rows"]["student"]["per_view"]["time_of_day"]) == 6
    stamp = (out / "rows" / "student.seed0.json").stat().st_mtime_ns
    assert main(["eval", "--report", "--evalset", str(clips), "--checkpoint", str(tiny_bundle), "--out", str(out)]) == 0
    assert (out / "rows" / "student.seed0.json").stat().st_mtime_ns == stamp
    assert json.loads((out / "report.json").read_text())["rows"] == report["rows"]
    # The DiTs' precision is part of a row's key: forcing bf16 regenerates the model rows only.
    oracle_stamp = (out / "rows" / "oracle.json").stat().st_mtime_ns
    old_key = json.loads((out / "rows" / "student.seed0.json").read_text())["key"]
    bf16 = ["--dtype", "bfloat16"]
    assert (
        main(["eval", "--report", "--evalset", str(clips), "--checkpoint", str(tiny_bundle), "--out", str(out), *bf16])
        == 0
    )
    assert json.loads((out / "rows" / "student.seed0.json").read_text())["key"] != old_key
    assert (out / "rows" / "oracle.json").stat().st_mtime_ns == oracle_stamp
    # Another rolling window for the student (a study knob) is part of the student rows' key too.
    bf16_key = json.loads((out / "rows" / "student.seed0.json").read_text())["key"]
    window = ["--dtype", "bfloat16", "--context-frames", "1"]
    args = ["eval", "--report", "--evalset", str(clips), "--checkpoint", str(tiny_bundle), "--out", str(out)]
    assert main([*args, *window]) == 0
    key = json.loads((out / "rows" / "student.seed0.json").read_text())["key"]
    assert key != bf16_key
    assert (out / "rows" / "oracle.json").stat().st_mtime_ns == oracle_stamp
    assert exit_status(main, [*args, "--context-frames", "0"]) == 2
    assert "argument --context-frames: must be a positive integer, got '0'" in capsys.readouterr().err
    capsys.readouterr()
    none = ["--clips-prefix", "long_"]
    assert (
        main(["eval", "--report", "--evalset", str(clips), "--checkpoint", str(tiny_bundle), "--out", str(out), *none])
        == 2
    )
    assert "no clips named long_*" in capsys.readouterr().err
    # Rows refreshing the context frame at some denoising steps only: one per --refresh-steps.
    assert main([*args, "--refresh-steps", "0", "--refresh-steps", "1,3"]) == 0
    rows = json.loads((out / "report.json").read_text())["rows"]
    assert {"student_refresh_0", "student_refresh_1_3"} <= set(rows)
    keys = {json.loads((out / "rows" / f"{r}.seed0.json").read_text())["key"] for r in rows if r.startswith("student")}
    assert len(keys) == 4  # student, no-refresh, refresh at 0, at 1 and 3: each its own cached row
    beyond = "--refresh-steps [9] names no step of the 4 denoising steps"
    for bad, says in (("9", beyond), ("first", "--refresh-steps")):
        assert exit_status(main, [*args, "--refresh-steps", bad]) == 2
        assert says in capsys.readouterr().err
    # Rows with an attention sink: with the bundle's own refresh and with each --refresh-steps row.
    assert main([*args, "--refresh-steps", "0", "--sink-frames", "1"]) == 0
    rows = json.loads((out / "report.json").read_text())["rows"]
    assert {"student_sink_1", "student_refresh_0_sink_1"} <= set(rows)
    sink_keys = {json.loads((out / "rows" / f"{r}.seed0.json").read_text())["key"] for r in rows if "sink" in r}
    assert len(sink_keys) == 2 and not sink_keys & keys
    assert exit_status(main, [*args, "--sink-frames", "65"]) == 2
    assert "--sink-frames must be an integer in [0, 64], got 65" in capsys.readouterr().err


def test_batched_student_row_equals_one_clip_at_a_time(tiny_bundle, tmp_path):
    import numpy as np

    from world_model.data import iter_clips
    from world_model.eval.report.rows import world_model_row
    from world_model.rollout.runtime import load_world_model

    for i, duration in enumerate(("0.6", "0.3")):  # clips of different lengths share a batch
        args = ["record", "--scenario", "merge_cut_in", "--episodes", "1", "--duration", duration]
        assert main([*args, "--out", str(tmp_path / f"d{i}"), "--height", "16", "--width", "32", "--seed", str(i)]) == 0
    clips = [c for i in range(2) for c in iter_clips(tmp_path / f"d{i}")]
    assert clips[0].num_frames != clips[1].num_frames
    row = world_model_row(load_world_model(tiny_bundle), seed=5, batch=2)
    together = row.generate_all(clips)
    for clip, gen in zip(clips, together, strict=True):
        alone = row(clip)
        assert gen.cameras.shape[0] == clip.num_frames
        assert gen.pass_starts == tuple(range(1, clip.num_frames))  # the tiny preset's 1-frame chunks
        assert np.abs(gen.cameras.astype(int) - alone.cameras).max() <= 1  # same noise, same frames
        assert np.allclose(gen.lidar, alone.lidar, atol=0.05)


def test_report_row_with_lora_adapters(tmp_path, capsys):
    """``--adapters``: an extra student_adapted row (the bundle's student with the adapters), keyed
    by the adapters' content; the plain student row stays the plain student."""
    import torch

    from tests.model_fixtures import perturbed
    from world_model.bundle import save_bundle
    from world_model.lora import LoraConfig, add_adapter, base_fingerprint, save_adapter
    from world_model.model import MultiViewDiT, SensorVAE, get_preset
    from world_model.rollout.runtime import load_world_model

    clips = tmp_path / "eval"
    rec = ["record", "--scenario", "merge_cut_in", "--episodes", "1", "--duration", "0.6", "--seed", "1000"]
    assert main([*rec, "--out", str(clips), "--height", "16", "--width", "32"]) == 0
    # An untrained student's zero-initialized output layer would hide any adapter: perturb it.
    cfg = get_preset("tiny").for_student()
    parts = {"vae": SensorVAE(cfg).state_dict(), "student": perturbed(MultiViewDiT(cfg)).state_dict()}
    tiny_bundle = save_bundle(tmp_path / "bundle", cfg.to_dict(), parts)
    student = load_world_model(tiny_bundle).student
    fingerprint = base_fingerprint(student)
    add_adapter(student, "van", LoraConfig())
    with torch.no_grad():
        for n, p in student.named_parameters():
            if "lora_B" in n:
                p.normal_(0.0, 0.5, generator=torch.Generator().manual_seed(len(n)))
    save_adapter(student, "van", tmp_path / "van", LoraConfig(), fingerprint)
    out = tmp_path / "report"
    args = ["eval", "--report", "--evalset", str(clips), "--checkpoint", str(tiny_bundle), "--out", str(out)]
    assert main([*args, "--adapters", str(tmp_path / "van")]) == 0
    rows = json.loads((out / "report.json").read_text())["rows"]
    assert set(rows) == {
        "oracle",
        "autoencoder",
        "road_only",
        "first_frame",
        "student",
        "student_no_refresh",
        "student_adapted",
    }
    assert rows["student_adapted"]["table1"]["psnr_db"] != rows["student"]["table1"]["psnr_db"]

    def key(row: str) -> str:
        return json.loads((out / "rows" / f"{row}.seed0.json").read_text())["key"]

    adapted_key = key("student_adapted")
    assert adapted_key != key("student")
    assert "| student_adapted |" in capsys.readouterr().out
    # Another adapter's content is another row key: the row is regenerated, the plain rows are kept.
    with torch.no_grad():
        for n, p in student.named_parameters():
            if "lora_B" in n:
                p.mul_(-1.0)
    save_adapter(student, "van", tmp_path / "van", LoraConfig(), fingerprint)
    assert main([*args, "--adapters", str(tmp_path / "van")]) == 0
    assert key("student_adapted") != adapted_key
    assert main([*args, "--adapters", "no_such_adapter"]) == 2
    assert "adapter 'no_such_adapter' not found" in capsys.readouterr().err


def test_student_row_marks_each_causal_chunk_for_the_chunk_jump_scores(tiny_bundle, tmp_path, monkeypatch):
    from dataclasses import replace

    from world_model.data import iter_clips
    from world_model.eval import evaluate_rows, load_default_judge
    from world_model.eval.report import ReportConfig
    from world_model.eval.report.rows import world_model_row
    from world_model.rollout.runtime import load_world_model
    from world_model.student.engine import StreamingEngine

    args = ["record", "--scenario", "merge_cut_in", "--episodes", "1", "--duration", "0.6", "--out", str(tmp_path)]
    assert main([*args, "--height", "16", "--width", "32"]) == 0
    (clip,) = iter_clips(tmp_path)
    wm = load_world_model(tiny_bundle)
    cfg = replace(wm.cfg, clip=replace(wm.cfg.clip, chunk_frames=2))  # weights do not depend on the chunking
    wm.student.cfg = cfg
    wm = replace(wm, cfg=cfg)
    passes = []
    real_denoise = StreamingEngine.denoise  # a chunk's generation, in step() or before a deferred commit

    def counted(self, controls, *a, **kw):
        passes.append(controls.num_frames)
        return real_denoise(self, controls, *a, **kw)

    monkeypatch.setattr(StreamingEngine, "denoise", counted)
    row = world_model_row(wm, seed=3)
    gen = row(clip)
    # frame 0 from the reference model, then one 2-frame chunk per engine step (the last one padded)
    assert passes == [2] * len(gen.pass_starts) and gen.pass_starts[:2] == (1, 3)
    assert 2 * len(passes) >= clip.num_frames - 1 > 2 * (len(passes) - 1)
    cfg = ReportConfig(frame_stride=3, lidar_stride=30, chamfer_max_points=256)
    t1 = evaluate_rows({"student": row}, [clip], judge=load_default_judge(), config=cfg).rows["student"].table1
    assert t1.chunk_jump_cameras > 0 and t1.chunk_jump_lidar > 0
