"""m4world bench first_frame on an untrained tiny bundle: one row per sampler setting, seeds."""

from m4world_env.bench.first_frame import main
from m4world_env.cli import main as cli


def test_first_frame_grid_is_judged_against_the_true_first_frames(tiny_bundle, tmp_path):
    clips = tmp_path / "eval"
    args = ["record", "--scenario", "merge_cut_in", "--episodes", "1", "--duration", "0.3", "--out", str(clips)]
    assert cli([*args, "--height", "16", "--width", "32", "--seed", "1000"]) == 0
    out = tmp_path / "ff.json"
    cmd = ["--evalset", str(clips), "--checkpoint", str(tiny_bundle), "--cfg", "1", "3", "--steps", "2"]
    result = main([*cmd, "--seeds", "2", "--out", str(out)])
    assert out.exists() and result["first_frames"] == 2
    assert list(result["rows"]) == ["oracle", "reference cfg=1 steps=2", "reference cfg=3 steps=2"]
    oracle, sampled = result["rows"]["oracle"], result["rows"]["reference cfg=3 steps=2"]
    assert oracle["psnr_db"] > sampled["psnr_db"] and oracle["lidar_mae_m"] == 0.0 < sampled["lidar_mae_m"]


def test_a_bundles_first_frame_model_gets_a_row(first_frame_bundle, tmp_path):
    clips = tmp_path / "eval"
    args = ["record", "--scenario", "merge_cut_in", "--episodes", "1", "--duration", "0.3", "--out", str(clips)]
    assert cli([*args, "--height", "16", "--width", "32", "--seed", "1000"]) == 0
    result = main(["--evalset", str(clips), "--checkpoint", str(first_frame_bundle), "--steps", "1", "--seeds", "2"])
    assert list(result["rows"])[-1] == "first_frame model, one step"
    one_step, reference = result["rows"]["first_frame model, one step"], result["rows"]["reference cfg=3 steps=1"]
    assert one_step["psnr_db"] != reference["psnr_db"]
