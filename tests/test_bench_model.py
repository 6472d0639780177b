"""benchmarks/bench_model.py end to end on the tiny preset: one row per dtype, sane fractions."""

import json
import subprocess
import sys
from pathlib import Path

from world_model.precision import cpu_has_native_bf16

ROOT = Path(__file__).resolve().parents[1]


def test_bench_model_reports_each_dtype_against_its_own_peak(tmp_path):
    # bf16 where the CPU multiplies it natively: emulated, its peak measurement alone takes minutes.
    dtypes = ("fp32", "bf16") if cpu_has_native_bf16() else ("fp32",)
    out = tmp_path / "model.json"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "bench_model.py"), "--presets", "tiny"]
    args = ["--dtypes", *dtypes, "--models", "student", "teacher", "--repeats", "1", "--out", str(out)]
    subprocess.run([*cmd, *args], check=True, cwd=ROOT)
    result = json.loads(out.read_text())
    assert {(r["model"], r["dtype"]) for r in result["presets"]} == {
        (m, d) for m in ("student", "teacher") for d in dtypes
    }
    rows = {r["dtype"]: r for r in result["presets"] if r["model"] == "student"}
    assert not any(r["compiled"] for r in rows.values())
    for dtype, row in rows.items():
        assert row["forward_gflop"] > 0 and row["forward_s"] > 0
        assert row["fraction_of_peak"] == row["achieved_gflops"] / result["peak_gflops"][dtype]


def test_bench_model_compares_heaps_in_fresh_processes(tmp_path):
    out = tmp_path / "heaps.json"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "bench_model.py"), "--presets", "tiny", "--dtypes", "fp32"]
    args = ["--heaps", "retain", "default", "--rounds", "1", "--repeats", "1", "--out", str(out)]
    subprocess.run([*cmd, *args], check=True, cwd=ROOT)
    result = json.loads(out.read_text())
    rows = {r["heap"]: r for r in result["presets"]}
    assert set(rows) == {"retain", "default"} and len(result["per_round"]) == 1
    assert rows["default"]["speedup_vs_default"] == 1.0
    assert rows["retain"]["page_faults_per_forward"] >= 0 and rows["retain"]["forward_s"] > 0
