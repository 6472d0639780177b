"""benchmarks/bench_model.py end to end on the tiny preset: one row per dtype, sane fractions."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_bench_model_reports_each_dtype_against_its_own_peak(tmp_path):
    out = tmp_path / "model.json"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "bench_model.py"), "--presets", "tiny"]
    subprocess.run([*cmd, "--dtypes", "fp32", "bf16", "--repeats", "1", "--out", str(out)], check=True, cwd=ROOT)
    result = json.loads(out.read_text())
    rows = {r["dtype"]: r for r in result["presets"]}
    assert set(rows) == {"fp32", "bf16"} and not any(r["compiled"] for r in rows.values())
    for dtype, row in rows.items():
        assert row["forward_gflop"] > 0 and row["forward_s"] > 0
        assert row["fraction_of_peak"] == row["achieved_gflops"] / result["peak_gflops"][dtype]
