"""benchmarks/bench_env.py end to end (procedural backend, small): interleaved rounds, medians, ratios."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


# Start the benchmark from a process that first grows to ~600 MB, as a long pytest run does: Linux
# keeps ru_maxrss across execve, so a peak read from it would be the launcher's.
BIG_LAUNCHER = "import os, sys; ballast = b'x' * (600 << 20); os.execv(sys.executable, [sys.executable, *sys.argv[1:]])"


def test_bench_env_reports_medians_of_interleaved_rounds(tmp_path):
    out = tmp_path / "env.json"
    cmd = [sys.executable, "-c", BIG_LAUNCHER, str(ROOT / "benchmarks" / "bench_env.py"), "--backend", "procedural"]
    cmd += ["--steps", "20"]
    subprocess.run([*cmd, "--rounds", "2", "--num-envs", "2", "--out", str(out)], check=True, cwd=ROOT)
    result = json.loads(out.read_text())
    assert result["rounds"] == 2 and len(result["per_round"]) == 2
    r = result["backends"]["procedural"]
    ratios = sorted(rnd["backends"]["procedural"]["single_vs_highway_fast_v0"] for rnd in result["per_round"])
    assert r["single_vs_highway_fast_v0"] == sum(ratios) / 2  # the median of two rounds
    assert r["num_envs"] == 2 and r["vector_aggregate_steps_per_s"] > 0 and r["one_env_peak_rss_mb"] > 0
    assert set(result["highway_env"]) == {"highway-v0", "highway-fast-v0"}
    # Timed in a fresh process per round (default): the parent never built an env of ours, and its
    # own peak does not include the launcher's 600 MB.
    assert result["peak_rss_mb"] < min(2 * r["one_env_peak_rss_mb"] + 200, 500)


def test_median_rounds_takes_the_median_of_nested_figures_too():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_env

    rounds = [
        {"steps_per_s": s, "num_envs": 8, "breakdown": {"student": st, "decode": 1.0}, "name": "x"}
        for s, st in ((3.0, 240.0), (1.0, 198.0), (2.0, 256.0))
    ]
    assert bench_env.median_rounds(rounds) == {
        "steps_per_s": 2.0,
        "num_envs": 8,
        "breakdown": {"student": 240.0, "decode": 1.0},
        "name": "x",
    }


def test_a_failing_backend_run_shows_its_own_error(tmp_path):
    cmd = [sys.executable, str(ROOT / "benchmarks" / "bench_env.py"), "--backend", "world_model", "--rounds", "1"]
    cmd += ["--steps", "2", "--num-envs", "1", "--checkpoint", str(tmp_path), "--out", str(tmp_path / "env.json")]
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    assert run.returncode != 0
    assert "is not a checkpoint bundle" in run.stderr  # the timed process's error, not just its exit status
    assert "world_model backend's run failed" in run.stderr and "CalledProcessError" not in run.stderr


def test_bench_env_in_process_and_memory_probe_reads_its_own_peak(tmp_path):
    out = tmp_path / "env.json"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "bench_env.py"), "--backend", "procedural", "--steps", "20"]
    subprocess.run([*cmd, "--rounds", "1", "--num-envs", "2", "--no-isolate", "--out", str(out)], check=True, cwd=ROOT)
    result = json.loads(out.read_text())
    r = result["backends"]["procedural"]
    # the probe's own peak, not the (bigger) parent's: Linux keeps ru_maxrss across execve
    assert 0 < r["one_env_peak_rss_mb"] < result["peak_rss_mb"]


def test_world_model_qualifiers_become_model_options():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_env

    from m4world_env.config import EnvConfig

    kw = bench_env._make_kwargs("world_model:compile:refresh=0,3", checkpoint=None)
    model = kw["config"]["model"]
    assert model == {"compile": True, "refresh_steps": [0, 3]}
    assert EnvConfig.from_dict(kw["config"]).model.refresh_steps == (0, 3)  # what gym.make gets
    assert bench_env._make_kwargs("world_model:no-refresh", None)["config"]["model"] == {"context_refresh": False}
    every = bench_env._make_kwargs("world_model:refresh=all", None)["config"]
    assert every["model"] == {"refresh_steps": "all"} and EnvConfig.from_dict(every).model.refresh_steps == "all"
    with pytest.raises(SystemExit, match="refresh=K"):
        bench_env._make_kwargs("world_model:refresh-first", None)
    sink = bench_env._make_kwargs("world_model:sink=1", None)["config"]
    assert sink["model"] == {"sink_frames": 1} and EnvConfig.from_dict(sink).model.sink_frames == 1
    with pytest.raises(SystemExit, match="sink=N"):
        bench_env._make_kwargs("world_model:sink=first", None)
    # a backend's own bundle overrides --checkpoint, so two checkpoints share one run's rounds
    kw = bench_env._make_kwargs("world_model:checkpoint=runs/x/bundle", checkpoint="other")
    assert kw["checkpoint"] == "runs/x/bundle" and "model" not in kw["config"]
    assert bench_env._make_kwargs("world_model", checkpoint="other")["checkpoint"] == "other"
    with pytest.raises(SystemExit, match="checkpoint=BUNDLE"):
        bench_env._make_kwargs("world_model:checkpoint=", None)


def test_world_model_step_breakdown_counts_the_condition_arrays(tiny_bundle):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_env

    r = bench_env.bench_backend("world_model", "merge_cut_in", 2, 2, 0, str(tiny_bundle), warmup=1, resets=0)
    part = r["vector_step_breakdown_ms_per_env_step"]
    assert part["conditions"] > 0 and part["student"] > 0 and part["decode"] > 0


def test_bench_workers_splits_a_step_and_hashes_the_same_observations(tiny_bundle):
    """bench_env --workers's probe: the parts of a vector step, and equal digests at 0 and 1 worker."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_env

    runs = {k: bench_env.bench_workers(k, "merge_cut_in", 2, 2, 1, 0, str(tiny_bundle)) for k in (0, 1)}
    assert runs[0]["digest"] == runs[1]["digest"]
    in_process, workers = (runs[k]["breakdown_ms_per_env_step"] for k in (0, 1))
    assert {"traffic", "crops", "conditions", "student", "decode", "other"} <= set(in_process)
    assert {"traffic", "conditions", "busy", "workers_wait", "student", "decode", "other"} <= set(workers)
    for parts in (in_process, workers):
        assert parts["traffic"] > 0 and parts["conditions"] > 0 and parts["non_model"] > 0
    assert workers["workers_wait"] + workers["other"] == pytest.approx(workers["non_model"])


def test_compare_workers_claims_equal_observations_only_when_it_compared_some(monkeypatch):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import argparse

    import bench_env

    def fake_run(workers, args, root):
        parts = {"non_model": 1.0}
        return {"non_model_env_steps_per_s": 10.0 + workers, "breakdown_ms_per_env_step": parts, "digest": "d"}

    monkeypatch.setattr(bench_env, "bench_workers_isolated", fake_run)

    def compare(workers, rounds):
        args = argparse.Namespace(workers=workers, rounds=rounds, compare_tree=None, scenario="s", device="cpu")
        return bench_env.compare_workers(args)["observations_identical"]

    assert compare([15], rounds=1) is None  # one run: nothing compared
    assert compare([15], rounds=2) is True  # the same count twice
    assert compare([0, 2], rounds=1) is True
    monkeypatch.setattr(bench_env, "bench_workers_isolated", lambda w, a, r: {**fake_run(w, a, r), "digest": f"d{w}"})
    assert compare([0, 2], rounds=1) is False
