"""The benchmarks' precision options: bench_env's dtype backend spec and precision_parity."""

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(ROOT / "benchmarks"))  # bench_env imports its sibling bench_traffic
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    return module


def test_bench_env_backend_spec_names_the_world_models_dtype():
    kwargs = _load("bench_env")._make_kwargs
    assert kwargs("world_model", None)["config"] == {"observation_keys": ["cameras", "lidar"]}
    forced = kwargs("world_model:bfloat16", "ckpt", compile_model=True)
    assert forced["backend"] == "world_model" and forced["checkpoint"] == "ckpt"
    assert forced["config"]["model"] == {"compile": True, "dtype": "bfloat16"}
    with pytest.raises(SystemExit, match="only the world_model backend"):
        kwargs("procedural:float32", None)


def test_bench_env_backend_spec_qualifiers_combine():
    kwargs = _load("bench_env")._make_kwargs
    model = kwargs("world_model:float32:compile:no-refresh", None)["config"]["model"]
    assert model == {"dtype": "float32", "compile": True, "context_refresh": False}
    on_gpu = kwargs("world_model", None, device="cuda")["config"]["model"]
    assert on_gpu == {"device": "cuda"}
    with pytest.raises(SystemExit, match="unknown qualifier 'fast'"):
        kwargs("world_model:fast", None)


def test_precision_parity_runs_one_episode_per_dtype(tiny_bundle, tmp_path):
    out = tmp_path / "parity.json"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "precision_parity.py"), "--checkpoint", str(tiny_bundle)]
    subprocess.run([*cmd, "--scenario", "merge_cut_in", "--steps", "2", "--out", str(out)], check=True, cwd=ROOT)
    result = json.loads(out.read_text())
    assert result["steps"] == 2 and [r["step"] for r in result["per_step"]] == [0, 1, 2]
    # bf16 weights and autocast move the tiny model's cameras: the option reached the env (its untrained
    # LiDAR decodes to the same ranges either way).
    assert result["max_camera_mean_abs_diff_levels"] > 0 and result["max_lidar_mean_abs_diff_m"] >= 0
