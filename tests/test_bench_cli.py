"""``m4world bench``: one benchmark with its own options, or the suite; each in a fresh process of
the installed package (no source checkout needed)."""

import importlib
import json
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import m4world_env.bench
from m4world_env.bench import BENCHMARKS, DEVICE_BENCHMARKS, SUITE, suite_command
from m4world_env.cli import main as cli

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def commands(monkeypatch):
    """The commands ``m4world bench`` starts, recorded instead of run (exit status 3)."""
    started = []

    def run(cmd, **_):
        started.append(cmd)
        return subprocess.CompletedProcess(cmd, 3)

    monkeypatch.setattr(subprocess, "run", run)
    return started


def test_every_benchmark_module_is_named_and_the_suite_runs_only_named_ones():
    modules = {m.name for m in pkgutil.iter_modules(m4world_env.bench.__path__)}
    assert modules == set(BENCHMARKS)
    assert set(SUITE) <= set(BENCHMARKS) and set(DEVICE_BENCHMARKS) <= set(SUITE)


@pytest.mark.parametrize("name", BENCHMARKS)
def test_every_benchmark_imports_and_names_itself(name, capsys):
    module = importlib.import_module(f"m4world_env.bench.{name}")
    with pytest.raises(SystemExit) as done:
        module.main(["--help"])
    assert done.value.code == 0 and capsys.readouterr().out.startswith(f"usage: m4world bench {name} ")


def test_one_benchmark_runs_with_its_own_options_and_its_exit_status(commands):
    assert cli(["bench", "reset", "--rounds", "2", "--out", "r.json"]) == 3
    assert commands == [[sys.executable, "-m", "m4world_env.bench.reset", "--rounds", "2", "--out", "r.json"]]


def test_the_suite_gives_each_its_file_and_the_device_to_those_that_take_one(commands, tmp_path):
    assert cli(["bench", "--only", "traffic", "env", "model", "--device", "cuda", "--out", str(tmp_path)]) == 0
    traffic, env, model = commands
    assert traffic == [sys.executable, "-m", "m4world_env.bench.traffic", "--out", str(tmp_path / "bench_traffic.json")]
    assert env[env.index("--device") + 1] == "cuda" and model[model.index("--device") + 1] == "cuda"
    assert env[-2:] == ["--out", str(tmp_path / "bench_env.json")]
    judge = suite_command("judge", tmp_path, "data/x", "cuda")
    assert "--device" not in judge and judge[judge.index("--evalset") + 1] == "data/x"
    with pytest.raises(ValueError, match="not in the suite"):
        suite_command("soak", tmp_path, "data/x", "cpu")


def test_suite_options_with_a_benchmarks_name_are_refused(commands, capsys):
    assert cli(["bench", "--device", "cuda", "env", "--rounds", "1"]) == 2
    assert "--device choose the suite's runs" in capsys.readouterr().err and not commands


def test_a_benchmark_runs_from_the_package(tmp_path):
    out = tmp_path / "traffic.json"
    cmd = [sys.executable, "-m", "m4world_env.cli", "bench", "traffic", "--steps", "3", "--out", str(out)]
    subprocess.run(cmd, check=True, cwd=ROOT, capture_output=True)
    result = json.loads(out.read_text())
    assert set(result) == {"machine", "bridge", "highway_env"} and result["bridge"]["merge_cut_in"]["steps_per_s"] > 0
