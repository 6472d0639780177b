"""m4world bench env end to end (procedural backend, small): interleaved rounds, medians, ratios."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from m4world_env.bench import env as bench_env

ROOT = Path(__file__).resolve().parents[1]  # the subprocesses' cwd: they import this checkout's packages
BENCH_ENV = [sys.executable, "-m", "m4world_env.bench.env"]


def test_bench_env_reports_medians_of_interleaved_rounds(tmp_path):
    out = tmp_path / "env.json"
    cmd = [*BENCH_ENV, "--backend", "procedural", "--steps", "20"]
    subprocess.run([*cmd, "--rounds", "2", "--num-envs", "2", "--out", str(out)], check=True, cwd=ROOT)
    result = json.loads(out.read_text())
    assert result["rounds"] == 2 and len(result["per_round"]) == 2
    r = result["backends"]["procedural"]
    rounds = [rnd["backends"]["procedural"] for rnd in result["per_round"]]
    assert r["single_vs_highway_fast_v0"] == sum(x["single_vs_highway_fast_v0"] for x in rounds) / 2  # median of two
    for x, rnd in zip(rounds, result["per_round"], strict=True):  # each ratio taken within its own round
        fast = rnd["highway_env"]["highway-fast-v0"]["steps_per_s"]
        assert x["single_vs_highway_fast_v0"] == x["single_steps_per_s"] / fast
        assert x["vector_aggregate_steps_per_s"] == pytest.approx(2e3 / x["vector_median_step_ms"])
    assert r["num_envs"] == 2 and set(result["highway_env"]) == {"highway-v0", "highway-fast-v0"}


def test_median_rounds_takes_the_median_of_nested_figures_too():
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
    cmd = [*BENCH_ENV, "--backend", "world_model", "--rounds", "1", "--steps", "2", "--num-envs", "1"]
    run = subprocess.run(
        [*cmd, "--checkpoint", str(tmp_path), "--out", str(tmp_path / "env.json")],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert run.returncode != 0
    assert "is not a checkpoint bundle" in run.stderr  # the timed process's error, not just its exit status
    assert "world_model backend's run failed" in run.stderr and "CalledProcessError" not in run.stderr


def test_the_peak_rss_is_the_status_files_high_water_mark():
    """VmHWM, the process's own peak: Linux keeps getrusage's ru_maxrss across execve, so a probe
    started by a big parent would report the parent's peak there."""
    status = "Name:\tpython\nVmPeak:\t 9000000 kB\nVmHWM:\t    2048 kB\nVmRSS:\t    1024 kB\n"
    assert bench_env.status_peak_rss_mb(status) == 2.0
    assert bench_env.status_peak_rss_mb("Name:\tpython\nVmRSS:\t 1024 kB\n") is None


def test_world_model_qualifiers_become_model_options():
    from m4world_env.config import EnvConfig

    kw = bench_env.make_kwargs("world_model:compile:refresh=0,3", checkpoint=None)
    model = kw["config"]["model"]
    assert model == {"compile": True, "refresh_steps": [0, 3]}
    assert EnvConfig.from_dict(kw["config"]).model.refresh_steps == (0, 3)  # what gym.make gets
    assert bench_env.make_kwargs("world_model:no-refresh", None)["config"]["model"] == {"context_refresh": False}
    for q, on in (("one-step-first", True), ("no-one-step-first", False)):
        assert bench_env.make_kwargs(f"world_model:{q}", None)["config"]["model"] == {"one_step_first_frame": on}
    every = bench_env.make_kwargs("world_model:refresh=all", None)["config"]
    assert every["model"] == {"refresh_steps": "all"} and EnvConfig.from_dict(every).model.refresh_steps == "all"
    with pytest.raises(SystemExit, match="refresh=K"):
        bench_env.make_kwargs("world_model:refresh-first", None)
    sink = bench_env.make_kwargs("world_model:sink=1", None)["config"]
    assert sink["model"] == {"sink_frames": 1} and EnvConfig.from_dict(sink).model.sink_frames == 1
    with pytest.raises(SystemExit, match="sink=N"):
        bench_env.make_kwargs("world_model:sink=first", None)
    fewer = bench_env.make_kwargs("world_model:keys=lidar+state:denoise=2:refresh=-1", None)["config"]
    assert fewer == {"observation_keys": ["lidar", "state"], "model": {"denoising_steps": 2, "refresh_steps": [-1]}}
    cfg = EnvConfig.from_dict(fewer)
    assert cfg.observation_keys == ("lidar", "state") and cfg.model.denoising_steps == 2
    with pytest.raises(SystemExit, match="denoise=N"):
        bench_env.make_kwargs("world_model:denoise=two", None)
    # a backend's own bundle overrides --checkpoint, so two checkpoints share one run's rounds
    kw = bench_env.make_kwargs("world_model:checkpoint=runs/x/bundle", checkpoint="other")
    assert kw["checkpoint"] == "runs/x/bundle" and "model" not in kw["config"]
    assert bench_env.make_kwargs("world_model", checkpoint="other")["checkpoint"] == "other"
    with pytest.raises(SystemExit, match="checkpoint=BUNDLE"):
        bench_env.make_kwargs("world_model:checkpoint=", None)


def test_world_model_step_breakdown_counts_the_condition_arrays(tiny_bundle):
    run = bench_env.BackendRun("merge_cut_in", 2, 2, 0, str(tiny_bundle), warmup=1, resets=0)
    r = bench_env.bench_backend("world_model", run)
    part = r["vector_step_breakdown_ms_per_env_step"]
    assert part["conditions"] > 0 and part["student"] > 0 and part["decode"] > 0


def test_bench_workers_splits_a_step_and_hashes_the_same_observations(tiny_bundle):
    """bench_env --workers's probe: the parts of a vector step, and equal digests at 0 and 1 worker."""
    runs = {k: bench_env.bench_workers(k, "merge_cut_in", 2, 2, 1, 0, str(tiny_bundle)) for k in (0, 1)}
    assert runs[0]["digest"] == runs[1]["digest"]
    in_process, workers = (runs[k]["breakdown_ms_per_env_step"] for k in (0, 1))
    assert {"traffic", "crops", "conditions", "student", "decode", "other"} <= set(in_process)
    assert {"traffic", "conditions", "busy", "workers_wait", "student", "decode", "other"} <= set(workers)
    for parts in (in_process, workers):
        assert parts["traffic"] > 0 and parts["conditions"] > 0 and parts["non_model"] > 0
    assert workers["workers_wait"] + workers["other"] == pytest.approx(workers["non_model"])


def test_compare_workers_claims_equal_observations_only_when_it_compared_some(monkeypatch):
    import argparse

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
