"""m4world bench model end to end on the tiny preset (one row per dtype, each against its own peak),
and how its heap comparison merges the fresh processes' rounds."""

import argparse
import json
import subprocess
import sys
from pathlib import Path

import pytest

from m4world_env.bench import model as bench_model
from world_model.precision import cpu_has_native_bf16

ROOT = Path(__file__).resolve().parents[1]  # the subprocess's cwd: it imports this checkout's packages


def test_bench_model_reports_each_dtype_against_its_own_peak(tmp_path):
    # bf16 where the CPU multiplies it natively: emulated, its peak measurement alone takes minutes.
    dtypes = ("fp32", "bf16") if cpu_has_native_bf16() else ("fp32",)
    out = tmp_path / "model.json"
    cmd = [sys.executable, "-m", "m4world_env.bench.model", "--presets", "tiny"]
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
        assert row["achieved_gflops"] == pytest.approx(row["forward_gflop"] / row["forward_s"])
        assert row["fraction_of_peak"] == row["achieved_gflops"] / result["peak_gflops"][dtype]


def _run(heap: str, forward_s: float, faults: float, peak: float) -> dict:
    """One process's ``run_rows`` result with one row."""
    row = {"preset": "tiny", "heap": heap, "forward_s": forward_s, "page_faults_per_forward": faults}
    row.update(dict.fromkeys(set(bench_model.NUMBERS) - set(row), 1.0))
    return {"threads": 2, "peak_gflops": {"fp32": peak}, "presets": [row]}


def test_heap_rounds_merge_into_medians_and_within_round_speedups():
    """A machine that slows down between rounds slows both heaps of a round alike: the speed-up is
    the median of the within-round ratios (2.0 here), not the ratio of the medians (1.5)."""
    rounds = [
        {"retain": _run("retain", 1.0, 10.0, 100.0), "default": _run("default", 2.0, 50.0, 90.0)},
        {"retain": _run("retain", 2.0, 30.0, 80.0), "default": _run("default", 4.0, 70.0, 110.0)},
        {"retain": _run("retain", 4.0, 20.0, 70.0), "default": _run("default", 3.0, 60.0, 95.0)},
    ]
    merged = bench_model.merge_heap_rounds(rounds, ["retain", "default"])
    retain, default = merged["presets"]
    assert (retain["heap"], default["heap"]) == ("retain", "default")
    assert retain["forward_s"] == 2.0 and default["forward_s"] == 3.0
    assert retain["page_faults_per_forward"] == 20.0 and default["page_faults_per_forward"] == 60.0
    assert retain["speedup_vs_default"] == 2.0 and default["speedup_vs_default"] == 1.0
    assert merged["peak_gflops"] == {"fp32": 92.5} and merged["per_round"] is rounds


def test_each_heap_runs_in_a_fresh_process_with_its_own_setting(monkeypatch):
    calls = []

    def fake_run(cmd, **_):
        calls.append(cmd)
        heap = cmd[cmd.index("--heaps") + 1]
        printed = "matmul peak: ...\n" + json.dumps(_run(heap, 1.0 if heap == "retain" else 3.0, 0.0, 50.0))
        return subprocess.CompletedProcess(cmd, 0, stdout=printed)

    monkeypatch.setattr(bench_model.subprocess, "run", fake_run)
    args = argparse.Namespace(
        presets=["tiny"], models=["student"], dtypes=["fp32"], heaps=["retain", "default"], rounds=2, repeats=1
    )
    args.device, args.compile = "cpu", False
    merged = bench_model.compare_heaps(args)
    assert [c[c.index("--heaps") + 1] for c in calls] == ["retain", "default"] * 2
    assert all(c[:3] == [sys.executable, "-m", "m4world_env.bench.model"] for c in calls)
    assert merged["presets"][0]["speedup_vs_default"] == pytest.approx(3.0)


def test_a_chunk_counts_its_refreshed_steps_one_frame_longer_and_the_cache_write():
    from world_model.streaming import StreamingConfig

    one_step = StreamingConfig(denoising_steps=1, refresh_steps=(-1,))
    assert bench_model.chunk_forwards(one_step, 2) == 1.5 + 1
    four_steps = StreamingConfig(denoising_steps=4, refresh_steps=(-2, -1))
    assert bench_model.chunk_forwards(four_steps, 2) == 2 * 1.5 + 2 + 1
    unrefreshed = StreamingConfig(denoising_steps=4, context_refresh=False)
    assert bench_model.chunk_forwards(unrefreshed, 2) == 4 + 1
