"""m4world bench vae on an untrained tiny bundle: PSNR, judged object and long-tail crops."""

import json
from pathlib import Path

from m4world_env.bench.vae import main
from m4world_env.cli import main as cli


def _record(out: Path, scenario: str, seed: int) -> Path:
    args = ["record", "--scenario", scenario, "--episodes", "1", "--duration", "2", "--out", str(out)]
    assert cli([*args, "--height", "16", "--width", "32", "--seed", str(seed)]) == 0
    return out


def test_vae_bench_judges_truth_and_autoencoded_crops(tiny_bundle, tmp_path, capsys):
    ordinary = _record(tmp_path / "ordinary", "highway_sunny_day", 1000)
    rare = _record(tmp_path / "rare", "tree_truck_highway", 1001)
    out = tmp_path / "bench"
    cmd = ["--vae", str(tiny_bundle), "--ordinary-data", str(ordinary), "--case-data", str(rare)]
    assert main([*cmd, "--frames", "4", "--min-box-px", "4", "--out", str(out)]) == 0
    row = json.loads((out / "bench_vae.json").read_text())["rows"][str(tiny_bundle)]
    assert row["object_crops"] > 0 and row["case_views"] > 0
    assert 0 < row["ordinary_psnr_db"] < 60  # an untrained VAE does not reproduce the frames
    for key in ("existence", "existence_truth", "case_yes", "case_yes_truth"):
        assert 0.0 <= row[key] <= 1.0
    assert str(tiny_bundle) in capsys.readouterr().out
