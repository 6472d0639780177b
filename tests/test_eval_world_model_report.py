"""`m4world eval --report` with a world-model bundle (untrained tiny: plumbing, shapes, rows)."""

import json

from m4world_env.cli import main


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
    assert main(["eval", "--report", "--evalset", str(clips), "--checkpoint", str(tiny_bundle), "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert set(report["rows"]) == {"oracle", "student", "student_no_refresh"}
    oracle, student = report["rows"]["oracle"]["table1"], report["rows"]["student"]["table1"]
    assert oracle["psnr_db"] > student["psnr_db"]  # an untrained model is far from the ground truth
    assert student["lidar_range_mae_m"] > oracle["lidar_range_mae_m"] == 0.0
    assert "student_no_refresh" in capsys.readouterr().out
